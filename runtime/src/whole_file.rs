//! Output files that appear whole or not at all. Each is written into a hidden temporary file beside its
//! path (`.NAME.XXXXXX.partial`) and renamed into place only once every byte has been flushed, so a full
//! disk, a write error or a crash midway never leaves a file that looks complete, and a reader sees the old
//! file or the new one, never half. A file dropped before [`OutputFile::finish`] is removed; one left by a
//! killed process keeps its `.partial` name.

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use tempfile::TempPath;

use crate::error::{check_output_folder, Error, Result};

/// A file being written to `path`: [`Write`] and [`Seek`] into it, then [`OutputFile::finish`].
pub struct OutputFile {
    path: PathBuf,
    /// The temporary file's bytes.
    temporary: BufWriter<File>,
    /// Its name, removed when dropped unless persisted.
    temporary_path: TempPath,
}

impl OutputFile {
    /// Starts writing `path` (its folder must exist).
    pub fn create(path: &Path) -> Result<OutputFile> {
        check_output_folder(path)?;
        let folder = match path.parent() {
            Some(folder) if !folder.as_os_str().is_empty() => folder,
            _ => Path::new("."),
        };
        let name = path.file_name().map_or("output".into(), |n| n.to_string_lossy());
        let temporary = tempfile::Builder::new()
            .prefix(&format!(".{name}."))
            .suffix(".partial")
            .tempfile_in(folder)
            .map_err(|e| Error::write(path, e))?;
        let (file, temporary_path) = temporary.into_parts();
        Ok(OutputFile {
            path: path.to_path_buf(),
            temporary: BufWriter::with_capacity(1 << 20, file),
            temporary_path,
        })
    }

    /// Flushes every byte and renames the file into place, readable by all (as files the process creates
    /// are); says what failed (a full disk, say) and leaves nothing behind when it does.
    pub fn finish(self) -> Result<()> {
        let path = self.path;
        let fail = |e: &dyn std::fmt::Display| Error::write(&path, e);
        let file = self.temporary.into_inner().map_err(|e| fail(e.error()))?;
        file.sync_data().map_err(|e| fail(&e))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let readable = std::fs::Permissions::from_mode(0o644);
            file.set_permissions(readable).map_err(|e| fail(&e))?;
        }
        self.temporary_path.persist(&path).map_err(|e| fail(&e.error))?;
        Ok(())
    }
}

impl Write for OutputFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.temporary.write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.temporary.flush()
    }
}

impl Seek for OutputFile {
    fn seek(&mut self, position: SeekFrom) -> std::io::Result<u64> {
        self.temporary.seek(position)
    }
}

/// Writes `bytes` as the whole of `path`, or nothing (see [`OutputFile`]).
pub fn write_whole(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut file = OutputFile::create(path)?;
    file.write_all(bytes).map_err(|e| Error::write(path, e))?;
    file.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn a_file_appears_whole_when_finished_and_not_at_all_when_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frames.gif");
        std::fs::write(&path, b"the old file").unwrap();
        let mut file = OutputFile::create(&path).unwrap();
        file.write_all(b"the new").unwrap();
        assert_eq!(
            std::fs::read(&path).unwrap(),
            b"the old file",
            "unfinished, the old file stays"
        );
        assert_eq!(names(dir.path()).len(), 2);
        drop(file);
        assert_eq!(names(dir.path()), ["frames.gif"], "a dropped file leaves nothing");
        write_whole(&path, b"the new file").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"the new file");
        assert_eq!(names(dir.path()), ["frames.gif"]);
    }

    #[test]
    fn a_file_that_cannot_be_put_in_place_names_its_path_and_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        // A folder stands where the file should go: the bytes are written, the rename fails.
        let path = dir.path().join("mesh.ply");
        std::fs::create_dir(&path).unwrap();
        let mut file = OutputFile::create(&path).unwrap();
        file.write_all(&[7; 10]).unwrap();
        let message = file.finish().unwrap_err().to_string();
        assert!(message.contains("mesh.ply"), "{message}");
        assert_eq!(names(dir.path()), ["mesh.ply"]);
        assert!(path.is_dir());
        let missing = OutputFile::create(&dir.path().join("no such folder").join("mesh.ply"));
        let message = missing.err().unwrap().to_string();
        assert!(message.contains("does not exist"), "{message}");
    }
}
