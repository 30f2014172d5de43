//! Crash-safe file replacement: readers see the old file or the new one, never half of one.
//! Every writer of the project (map store, KITTI writer, generator, exporter of reports) uses it.
//!
//! Temp files are named `.<name>.tmp-<pid>-<n>-<random>` in the target's directory, created
//! exclusively (`O_EXCL`: two processes never share one, even with equal pids in different
//! containers) and held under an exclusive advisory lock (`flock`) from creation until the rename.
//! So a temp file whose lock can be taken belongs to no live writer: [`remove_orphaned_temp_files`]
//! deletes only those, and never another live process's in-progress write (replicas sharing a
//! map directory). The lock dies with its process, however it dies. On a filesystem without
//! `flock` support, writes go ahead unlocked and the sweep leaves such files alone.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

/// The marker in every temp file name (after the leading `.<name>`).
const TEMP_MARKER: &str = ".tmp-";

/// Writes `bytes` to a locked temporary file in the same directory, fsyncs it, renames it over
/// `path`, then fsyncs the directory so the rename itself is durable.
/// Errors name the file, so callers can pass them on as they are.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let named = |e: std::io::Error| std::io::Error::new(e.kind(), format!("writing {}: {e}", path.display()));
    let (mut file, tmp) = create_locked_temp(dir, name).map_err(named)?;
    let result = (|| {
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)?;
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    drop(file); // releases the lock, once the temp name is gone
    result.map_err(named)
}

/// A new, exclusively created and locked temp file for `name` in `dir`. A sweep may take a file
/// between its creation and our lock; then the path no longer names our file and we start over.
fn create_locked_temp(dir: &Path, name: &str) -> std::io::Result<(File, PathBuf)> {
    for _ in 0..16 {
        let at = dir.join(format!(".{name}{TEMP_MARKER}{}-{}-{:08x}", std::process::id(), unique(), rand::random::<u32>()));
        let file = match File::options().write(true).create_new(true).open(&at) {
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            other => other?,
        };
        match file.try_lock() {
            Ok(()) if same_file(&file, &at) => return Ok((file, at)),
            // Swept before we locked it (gone), or held by the sweep that is deleting it.
            Ok(()) | Err(std::fs::TryLockError::WouldBlock) => continue,
            // A filesystem without locks: write unprotected, as before locks were used.
            Err(std::fs::TryLockError::Error(e)) => {
                tracing::debug!("cannot lock {}: {e}; writing without a lock", at.display());
                return Ok((file, at));
            }
        }
    }
    Err(std::io::Error::other("could not create a temporary file that stays ours"))
}

/// Deletes the temp files in `dir` that no live writer holds (left by a crash or a kill) and
/// returns how many. A file being written by any process, this one or another sharing the
/// directory, is locked and left alone.
pub fn remove_orphaned_temp_files(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if !(name.starts_with('.') && name.contains(TEMP_MARKER)) {
            continue;
        }
        let path = entry.path();
        let Ok(file) = File::open(&path) else { continue };
        // Held: a live writer's. Taken: its writer is gone; the lock keeps a new writer from
        // reusing it while we delete it (it never would: names are created exclusively).
        // An error other than "held" (no lock support) tells nothing: leave the file.
        if file.try_lock().is_ok() && same_file(&file, &path) && std::fs::remove_file(&path).is_ok() {
            tracing::info!("removed orphaned temporary file {}", path.display());
            removed += 1;
        }
    }
    removed
}

/// Whether `path` still names the open `file` (not deleted or replaced since it was opened).
fn same_file(file: &File, path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (file.metadata(), std::fs::metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = file;
        path.exists()
    }
}

fn unique() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    COUNTER.fetch_add(1, Ordering::Relaxed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_and_leaves_no_temp_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn the_sweep_removes_orphans_and_spares_a_live_writers_file() {
        let dir = tempfile::tempdir().unwrap();
        let orphan = dir.path().join(".a.bin.tmp-1-0-00000000");
        std::fs::write(&orphan, b"left by a crash").unwrap();
        // A writer in the middle of its write (flock locks conflict between open files, so this
        // is what another process's lock looks like to the sweep).
        let (held, live) = create_locked_temp(dir.path(), "b.bin").unwrap();
        let unrelated = dir.path().join("c.bin");
        std::fs::write(&unrelated, b"x").unwrap();

        assert_eq!(remove_orphaned_temp_files(dir.path()), 1);
        assert!(!orphan.exists());
        assert!(live.exists(), "a locked temp file is another writer's");
        assert!(unrelated.exists());
        drop(held);
        assert_eq!(remove_orphaned_temp_files(dir.path()), 1, "once its writer is gone, it is an orphan");
        assert!(!live.exists());
    }
}
