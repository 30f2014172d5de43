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
    let mut writer = AtomicWriter::create(path)?;
    writer.write_all(bytes).map_err(|e| std::io::Error::new(e.kind(), format!("writing {}: {e}", path.display())))?;
    writer.commit()
}

/// A file written in pieces (too large to hold in memory) that replaces `path` only on
/// [`AtomicWriter::commit`]: the same locked temp file, fsync and renames as [`write_atomic`].
/// Dropped without a commit, it removes its temp file and `path` is untouched.
pub struct AtomicWriter {
    file: Option<std::io::BufWriter<File>>,
    tmp: PathBuf,
    path: PathBuf,
}

impl AtomicWriter {
    pub fn create(path: &Path) -> std::io::Result<Self> {
        let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
        let (file, tmp) = create_locked_temp(dir, name).map_err(|e| std::io::Error::new(e.kind(), format!("writing {}: {e}", path.display())))?;
        Ok(Self { file: Some(std::io::BufWriter::with_capacity(1 << 20, file)), tmp, path: path.to_path_buf() })
    }

    /// The file this will replace.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes and fsyncs the temp file, so a later [`AtomicWriter::commit`] (which fsyncs again)
    /// has little left to wait for: the slow part can run outside a caller's lock.
    pub fn sync(&mut self) -> std::io::Result<()> {
        let file = self.file.as_mut().expect("not yet committed");
        file.flush()?;
        file.get_ref().sync_all()
    }

    /// Flushes, fsyncs, renames over the target and fsyncs the directory.
    pub fn commit(mut self) -> std::io::Result<()> {
        let named = |e: std::io::Error| std::io::Error::new(e.kind(), format!("writing {}: {e}", self.path.display()));
        let buffered = self.file.take().expect("not yet committed");
        let result = (|| {
            let file = buffered.into_inner().map_err(|e| e.into_error())?;
            file.sync_all()?;
            std::fs::rename(&self.tmp, &self.path)?;
            let dir = self.path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
            if let Ok(d) = File::open(dir) {
                let _ = d.sync_all();
            }
            drop(file); // releases the lock, once the temp name is gone
            Ok(())
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        result.map_err(named)
    }
}

impl Write for AtomicWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.file.as_mut().expect("not yet committed").write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file.as_mut().expect("not yet committed").flush()
    }
}

impl Drop for AtomicWriter {
    fn drop(&mut self) {
        if self.file.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
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
        let mut abandoned = AtomicWriter::create(&p).unwrap();
        abandoned.write_all(b"three").unwrap();
        drop(abandoned);
        assert_eq!(std::fs::read(&p).unwrap(), b"two", "an uncommitted writer leaves the file alone");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "and its temp file is gone");
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
