//! Files a plugin reads because its options name them.

use std::io::{Error, ErrorKind, Read};
use std::path::Path;

/// The bytes of the regular file at `path`, of at most `limit` bytes.
///
/// Not `fs::read`: opening a FIFO waits for a writer that may never come, and a device
/// such as `/dev/zero` never ends; either would hold start-up. A path that is no regular
/// file is an [`ErrorKind::InvalidInput`] error saying so; a file larger than `limit` is
/// an [`ErrorKind::InvalidData`] error, refused by its size before a byte is read (the
/// read also stops one byte past `limit`, for a file that grows meanwhile).
///
/// ```
/// let dir = std::env::temp_dir();
/// let err = aimrt_plugin_api::read_regular_file(&dir, 1024).unwrap_err();
/// assert!(err.to_string().contains("it is not a regular file"));
/// ```
pub fn read_regular_file(path: &Path, limit: u64) -> std::io::Result<Vec<u8>> {
    let too_large = || {
        Error::new(
            ErrorKind::InvalidData,
            format!("it holds more than {limit} bytes"),
        )
    };
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(Error::new(
            ErrorKind::InvalidInput,
            "it is not a regular file (a directory, a pipe or a device)",
        ));
    }
    if meta.len() > limit {
        return Err(too_large());
    }
    let mut bytes = Vec::new();
    std::fs::File::open(path)?
        .take(limit + 1)
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(too_large());
    }
    Ok(bytes)
}
