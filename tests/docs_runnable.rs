//! The command blocks of the README and the docs that are fenced as ```` ```bash runnable ````
//! run as written, each from a fresh temporary directory laid out like a checkout, so they cannot
//! drift from the product.
//!
//! The directory holds links to what a checkout has and a block only reads (`models/`,
//! `runtime/`, `scripts/`, `examples/`, `.venv/`, `training/cmr/`, `web/`), a copy of the demo
//! region (`maps/demo.bin`, `maps/demo.json`), and `target/release/cmr-agent`: this build's
//! binary. A block runs under `bash -euo pipefail` with a 10-minute limit (30 for a slow one); whatever it starts in
//! the background is stopped when it ends. The one change made to the text: port 8099, the
//! docs' port for a server of their own, becomes a free one, so the test never meets another
//! server. Blocks fenced ```` ```bash runnable slow ```` (minutes on 2 cores: the fine-tune) run
//! only with `CMR_DOCS_SLOW=1`; blocks that use `jq`, `curl` or `../.venv` say SKIPPED, and
//! why, when those are missing (with `CMR_REQUIRE_DOCS=1` they fail instead).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
/// The port the docs give a server of their own.
const DOCS_PORT: &str = "8099";

/// Writes past the test harness's output capture, so a skip is never silent.
fn say(line: &str) {
    let _ = writeln!(std::io::stderr(), "{line}");
}

#[derive(Debug)]
struct Block {
    /// `file:line` of the opening fence.
    at: String,
    slow: bool,
    text: String,
}

/// Every ```` ```bash runnable ```` block of `text` (`name` for messages).
fn runnable_blocks(name: &str, text: &str) -> Vec<Block> {
    let mut blocks = Vec::new();
    let mut open: Option<Block> = None;
    for (i, line) in text.lines().enumerate() {
        let fence = line.trim();
        if let Some(block) = open.as_mut() {
            if fence == "```" {
                blocks.extend(open.take());
            } else {
                block.text.push_str(line);
                block.text.push('\n');
            }
            continue;
        }
        let mut words = fence.strip_prefix("```").unwrap_or("").split_whitespace();
        if words.next() == Some("bash") && words.next() == Some("runnable") {
            let slow = words.next() == Some("slow");
            open = Some(Block { at: format!("{name}:{}", i + 1), slow, text: String::new() });
        }
    }
    assert!(open.is_none(), "{name}: a runnable block is not closed");
    blocks
}

fn documents() -> Vec<PathBuf> {
    let root = Path::new(ROOT);
    let mut files = vec![root.join("README.md"), root.join("training/README.md")];
    let mut docs: Vec<PathBuf> =
        std::fs::read_dir(root.join("docs")).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|x| x == "md")).collect();
    docs.sort();
    files.extend(docs);
    files
}

fn on_path(program: &str) -> bool {
    std::env::var_os("PATH").is_some_and(|path| std::env::split_paths(&path).any(|dir| dir.join(program).is_file()))
}

/// A fresh directory laid out like a checkout (see the module's docs).
fn checkout_like(dir: &Path) {
    let root = Path::new(ROOT);
    std::fs::create_dir_all(dir.join("target/release")).unwrap();
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_cmr-agent"), dir.join("target/release/cmr-agent")).unwrap();
    for linked in ["models", "runtime", "scripts", "examples", ".venv", "web"] {
        if root.join(linked).exists() {
            std::os::unix::fs::symlink(root.join(linked), dir.join(linked)).unwrap();
        }
    }
    std::fs::create_dir_all(dir.join("training")).unwrap();
    std::os::unix::fs::symlink(root.join("training/cmr"), dir.join("training/cmr")).unwrap();
    std::fs::create_dir_all(dir.join("maps")).unwrap();
    for f in ["demo.bin", "demo.json"] {
        std::fs::copy(root.join("maps").join(f), dir.join("maps").join(f)).unwrap();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Why `block` cannot run here, if it cannot.
fn missing(block: &Block) -> Option<String> {
    let mut why = Vec::new();
    for tool in ["jq", "curl", "python3"] {
        if block.text.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).any(|w| w == tool) && !on_path(tool) {
            why.push(format!("no `{tool}` on PATH"));
        }
    }
    if block.text.contains(".venv/bin/python") && !Path::new(ROOT).join(".venv/bin/python").exists() {
        why.push("no .venv (make python)".into());
    }
    if !Path::new(ROOT).join("runtime").exists() {
        why.push("no runtime/ (make runtime)".into());
    }
    (!why.is_empty()).then(|| why.join("; "))
}

#[test]
fn runnable_doc_blocks_run_as_written() {
    let required = std::env::var("CMR_REQUIRE_DOCS").is_ok_and(|v| v == "1");
    let slow = std::env::var("CMR_DOCS_SLOW").is_ok_and(|v| v == "1");
    let blocks: Vec<Block> = documents()
        .iter()
        .flat_map(|path| {
            let name = path.strip_prefix(ROOT).unwrap().display().to_string();
            runnable_blocks(&name, &std::fs::read_to_string(path).unwrap())
        })
        .collect();
    assert!(blocks.len() >= 3, "the runnable blocks were not found: {blocks:?}");
    let mut failures = Vec::new();
    for block in &blocks {
        if block.slow && !slow {
            say(&format!("docs_runnable: {} SKIPPED (slow; CMR_DOCS_SLOW=1 runs it)", block.at));
            continue;
        }
        if let Some(why) = missing(block) {
            say(&format!("docs_runnable: {} SKIPPED: {why}", block.at));
            assert!(!required, "{}: {why}, and CMR_REQUIRE_DOCS=1", block.at);
            continue;
        }
        let dir = tempfile::tempdir().unwrap();
        checkout_like(dir.path());
        let script = format!(
            "set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n{}",
            block.text.replace(DOCS_PORT, &free_port().to_string())
        );
        let started = Instant::now();
        let limit = if block.slow { "1800" } else { "600" };
        let out = Command::new("timeout")
            .args(["--kill-after=10", limit, "bash", "-c", &script])
            .current_dir(dir.path())
            .env_remove("CMR_PORT")
            .env_remove("CMR_MAPS")
            .env_remove("CMR_MODELS")
            .output()
            .expect("bash and coreutils' timeout");
        let seconds = started.elapsed().as_secs_f64();
        let stdout = String::from_utf8_lossy(&out.stdout);
        say(&format!("docs_runnable: {} ran in {seconds:.1} s, exit {:?}; its output:\n{stdout}", block.at, out.status.code()));
        if !out.status.success() {
            let stderr = String::from_utf8_lossy(&out.stderr);
            let tail: Vec<&str> = stderr.lines().rev().take(30).collect::<Vec<_>>().into_iter().rev().collect();
            failures.push(format!("{} exited with {:?}:\n{}", block.at, out.status.code(), tail.join("\n")));
        }
    }
    assert!(failures.is_empty(), "runnable doc blocks failed:\n\n{}", failures.join("\n\n"));
}

#[test]
fn blocks_are_found_with_their_line() {
    let text = "intro\n```bash runnable\necho one\n```\n```bash\nnot this\n```\n```bash runnable slow\necho two\n```\n";
    let blocks = runnable_blocks("x.md", text);
    assert_eq!(blocks.len(), 2);
    assert_eq!((blocks[0].at.as_str(), blocks[0].slow, blocks[0].text.as_str()), ("x.md:2", false, "echo one\n"));
    assert_eq!((blocks[1].at.as_str(), blocks[1].slow, blocks[1].text.as_str()), ("x.md:8", true, "echo two\n"));
}
