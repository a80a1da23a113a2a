//! The error type of the runtime: every fallible function returns [`Result`].

use std::fmt;
use std::path::{Path, PathBuf};

/// What went wrong, with enough context (file, key, value) to fix it.
#[derive(Debug, Clone, PartialEq)]
pub enum Error {
    /// A file could not be read or written.
    Io {
        /// `"read"` or `"write"`.
        action: &'static str,
        /// The file concerned.
        path: PathBuf,
        /// Why, e.g. "folder 'out' does not exist".
        reason: String,
    },
    /// A file was read but its content is not what was expected.
    Format {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong, e.g. `cameras[2]: missing key 'eye'`.
        reason: String,
    },
    /// An argument is out of range, e.g. a 0×0 image or a degenerate camera.
    Invalid(String),
}

/// Shorthand for results whose error is [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// An error reading `path`.
    pub(crate) fn read(path: &Path, reason: impl fmt::Display) -> Error {
        Error::Io {
            action: "read",
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }

    /// An error reading `path`, saying "file not found" when it does not exist.
    pub(crate) fn reading(path: &Path, e: std::io::Error) -> Error {
        match e.kind() {
            std::io::ErrorKind::NotFound => Error::read(path, "file not found"),
            _ => Error::read(path, e),
        }
    }

    /// An error writing `path`.
    pub(crate) fn write(path: &Path, reason: impl fmt::Display) -> Error {
        Error::Io {
            action: "write",
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }

    /// Bad content in `path`.
    pub(crate) fn format(path: &Path, reason: impl fmt::Display) -> Error {
        Error::Format {
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Io { action, path, reason } => write!(f, "cannot {action} {}: {reason}", path.display()),
            Error::Format { path, reason } => write!(f, "{}: {reason}", path.display()),
            Error::Invalid(message) => f.write_str(message),
        }
    }
}

impl std::error::Error for Error {}

/// Checks that an image size is usable (both sides at least 1 pixel).
pub(crate) fn check_size(width: u32, height: u32) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::Invalid(format!(
            "image size {width}×{height} is empty: width and height must be at least 1"
        )));
    }
    Ok(())
}

/// Checks that the folder `path` would be written into exists, with an error naming it.
pub(crate) fn check_output_folder(path: &Path) -> Result<()> {
    if let Some(folder) = path.parent() {
        if !folder.as_os_str().is_empty() && !folder.is_dir() {
            return Err(Error::write(
                path,
                format!("folder '{}' does not exist", folder.display()),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_name_the_file_and_the_problem() {
        let e = Error::write(Path::new("out/x.gif"), "folder 'out' does not exist");
        assert_eq!(
            e.to_string(),
            "cannot write out/x.gif: folder 'out' does not exist"
        );
        let e = Error::format(Path::new("a.json"), "missing key 'eye'");
        assert_eq!(e.to_string(), "a.json: missing key 'eye'");
    }

    #[test]
    fn empty_sizes_are_rejected() {
        assert!(check_size(0, 4).is_err());
        assert!(check_size(4, 0).is_err());
        assert!(check_size(1, 1).is_ok());
    }
}
