//! Finding and loading ONNX Runtime's shared library (`ort` with `load-dynamic`).
//!
//! ONNX Runtime allows one environment per process, so it lives in a process-wide cell; every
//! backend (one per worker thread) creates its sessions in it.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{Context, Result, anyhow, bail};
use ort::environment::Environment;

const LIB_NAME: &str = "libonnxruntime.so";

static ENVIRONMENT: OnceLock<(PathBuf, Environment)> = OnceLock::new();
static INIT: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Where to look for the library, in order: the explicit flag, `ORT_DYLIB_PATH`, `runtime/`
/// under the current directory, then `runtime/` two levels above the executable (so
/// `target/release/cmr-agent` finds the project's `runtime/`).
pub fn candidate_paths(explicit: Option<&Path>) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Some(p) = explicit {
        out.push(p.to_path_buf());
        return out;
    }
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(p));
        return out;
    }
    if let Ok(cwd) = std::env::current_dir() {
        out.push(cwd.join("runtime").join(LIB_NAME));
    }
    if let Some(dir) = std::env::current_exe().ok().and_then(|e| e.parent().map(Path::to_path_buf)) {
        out.push(dir.join("../../runtime").join(LIB_NAME));
        out.push(dir.join(LIB_NAME));
    }
    out
}

/// The process's ONNX Runtime environment, created on first use from the first library found.
pub fn environment(explicit: Option<&Path>) -> Result<&'static Environment> {
    if let Some((_, env)) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let _guard = INIT.lock().map_err(|_| anyhow!("ONNX Runtime initialisation panicked earlier"))?;
    if let Some((_, env)) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let candidates = candidate_paths(explicit);
    let Some(path) = candidates.iter().find(|p| p.is_file()) else {
        let tried: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
        bail!(
            "ONNX Runtime library not found (tried: {}); run `make runtime` (scripts/install-onnxruntime.sh) \
             or pass --ort-lib / set ORT_DYLIB_PATH",
            tried.join(", ")
        );
    };
    let builder = ort::init_from(path)
        .map_err(|e| anyhow!("cannot load ONNX Runtime from {}: {e}", path.display()))?;
    let env = builder
        .with_name("cmr-agent")
        .with_telemetry(false)
        .build()
        .map_err(|e| anyhow!("cannot create the ONNX Runtime environment from {}: {e}", path.display()))?;
    let _ = ENVIRONMENT.set((path.clone(), env));
    Ok(&ENVIRONMENT.get().context("environment vanished")?.1)
}

/// The library the environment was loaded from, once it exists.
pub fn loaded_library() -> Option<&'static Path> {
    ENVIRONMENT.get().map(|(p, _)| p.as_path())
}
