//! The lock of the folder a training run or a render writes into. Two of them writing into one folder at
//! once would overwrite each other's files (a checkpoint, a log, frames), so the second refuses, naming the
//! first. The lock is
//! the operating system's advisory lock (`flock`) on `<folder>/.nerfjit.lock`: it ends with the process that
//! holds it, however the process ends (`kill -9` and crashes included), so no lock is ever left stuck. The
//! file stays (removing it could let two runs lock two different files); its text says who holds it.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use crate::failure::{Failure, Result};

/// The name of the lock file in a locked folder.
pub const LOCK_FILE: &str = ".nerfjit.lock";

/// A folder locked by this process until the lock is dropped.
#[derive(Debug)]
pub struct FolderLock {
    /// The open lock file: the lock lives as long as it is open.
    _file: File,
}

impl FolderLock {
    /// Locks `folder` for `what` this process does in it, or says which process holds it.
    pub fn take(folder: &Path, what: &str) -> Result<FolderLock> {
        let path = folder.join(LOCK_FILE);
        let failed = |e: std::io::Error| Failure::Message(format!("cannot lock '{}': {e}", folder.display()));
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(failed)?;
        match file.try_lock() {
            Ok(()) => {
                let holder = format!("pid {}: {what}\n", std::process::id());
                file.set_len(0).map_err(failed)?;
                file.rewind().map_err(failed)?;
                file.write_all(holder.as_bytes()).map_err(failed)?;
                Ok(FolderLock { _file: file })
            }
            Err(TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.take(1000).read_to_string(&mut holder);
                let holder = match holder.trim() {
                    "" => "another process".to_string(),
                    text => text.to_string(),
                };
                Err(Failure::Message(format!(
                    "'{}' is in use by another nerfjit run or render ({holder}): writing there too would overwrite \
                     its files; wait for it to end, or write into another folder (--out DIR)",
                    folder.display()
                )))
            }
            Err(TryLockError::Error(e)) => Err(failed(e)),
        }
    }
}

/// Locks the folders that `files` (a training run's checkpoint and metrics log, a render's frames) are
/// written into, each once, for this process's command line. On the ranks of an MPI job other than rank 0,
/// which write none of them, nothing is locked; a folder that does not exist yet is not either (nobody
/// else writes there yet).
pub fn lock_output_folders<'a>(files: impl IntoIterator<Item = &'a Path>) -> Result<Vec<FolderLock>> {
    if crate::cluster::current().rank() != 0 {
        return Ok(Vec::new());
    }
    let mut folders: Vec<PathBuf> = files
        .into_iter()
        .filter_map(|file| {
            let folder = file
                .parent()
                .filter(|f| !f.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            std::fs::canonicalize(folder).ok()
        })
        .collect();
    folders.sort();
    folders.dedup();
    let what = std::env::args().collect::<Vec<_>>().join(" ");
    folders
        .iter()
        .map(|folder| FolderLock::take(folder, &what))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_locked_folder_is_refused_with_its_holder_until_the_lock_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let first = FolderLock::take(dir.path(), "nerfjit run first.sdf").unwrap();
        let err = FolderLock::take(dir.path(), "nerfjit run second.sdf")
            .unwrap_err()
            .to_string();
        assert!(err.contains("in use by another nerfjit run or render"), "{err}");
        assert!(
            err.contains(&format!("pid {}: nerfjit run first.sdf", std::process::id())),
            "{err}"
        );
        drop(first);
        let again = FolderLock::take(dir.path(), "nerfjit run second.sdf").unwrap();
        drop(again);
        let text = std::fs::read_to_string(dir.path().join(LOCK_FILE)).unwrap();
        assert!(text.ends_with(": nerfjit run second.sdf\n"), "{text}");
    }

    #[test]
    fn a_run_locks_each_folder_of_its_files_once() {
        let dir = tempfile::tempdir().unwrap();
        let (checkpoint, log) = (dir.path().join("run.ckpt"), dir.path().join(".").join("run.log"));
        let locks = lock_output_folders([checkpoint.as_path(), log.as_path()]).unwrap();
        assert_eq!(locks.len(), 1);
        let err = lock_output_folders([checkpoint.as_path()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("in use by another nerfjit run or render"), "{err}");
        drop(locks);
        assert_eq!(lock_output_folders([log.as_path()]).unwrap().len(), 1);
        let missing = dir.path().join("not yet").join("run.ckpt");
        assert!(lock_output_folders([missing.as_path()]).unwrap().is_empty());
    }
}
