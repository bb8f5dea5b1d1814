//! Reading the files a cell file is made of (the cell file itself, the users file, PEM files)
//! with a bound: only a regular file is read, never more than its bound, and opening one never
//! waits. A FIFO put in the cell file's place would otherwise hold a reload until something
//! writes to it, and a link to `/dev/zero` would be read until memory runs out.

use std::io::Read as _;
use std::os::unix::fs::OpenOptionsExt as _;
use std::path::Path;

/// The largest cell file read: a cell of 1 024 machines is about 250 KiB.
pub const MAX_CELL_FILE: u64 = 4 * 1024 * 1024;
/// The largest users file or PEM file read.
pub const MAX_SIDE_FILE: u64 = 1024 * 1024;

/// The bytes of the regular file at `path` (a symbolic link is followed: a mounted
/// configuration is often one), at most `max` of them, or why not. Blocking, but never on
/// the file's kind: `O_NONBLOCK` makes opening a FIFO or a device return at once, and the
/// open file is checked before a byte is read.
pub fn read_bounded(path: &Path, max: u64) -> std::io::Result<Vec<u8>> {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("it is {}, not a regular file", kind(&meta.file_type())),
        ));
    }
    if meta.len() > max {
        return Err(too_large(meta.len(), max));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // The file may grow while it is read: never past the bound.
    file.take(max + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64, max));
    }
    Ok(bytes)
}

/// [`read_bounded`] as UTF-8 text.
pub fn read_text_bounded(path: &Path, max: u64) -> std::io::Result<String> {
    String::from_utf8(read_bounded(path, max)?).map_err(|e| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "it is not UTF-8 text (byte {})",
                e.utf8_error().valid_up_to()
            ),
        )
    })
}

fn too_large(size: u64, max: u64) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!("it holds {size} bytes or more, over the {max} bytes read at most"),
    )
}

/// What a file that is not a regular one is, for a message.
pub fn kind(t: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt as _;
    if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_symlink() {
        "a symbolic link"
    } else {
        "not a regular file"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_are_read_and_never_past_their_bound() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("cell.toml");
        std::fs::write(&file, "cell = \"x\"\n").unwrap();
        assert_eq!(read_text_bounded(&file, 64).unwrap(), "cell = \"x\"\n");
        // Over the bound: refused before it is read.
        let e = read_bounded(&file, 4).unwrap_err();
        assert!(e.to_string().contains("over the 4 bytes"), "{e}");
        // A FIFO: refused at once, with nothing writing to it.
        let fifo = dir.path().join("fifo");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        assert!(made.unwrap().success());
        let e = read_bounded(&fifo, 64).unwrap_err();
        assert!(e.to_string().contains("a FIFO"), "{e}");
        // A link to an endless device: refused, not read.
        let zero = dir.path().join("zero");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let e = read_bounded(&zero, 64).unwrap_err();
        assert!(e.to_string().contains("character device"), "{e}");
        // A link to a regular file is followed.
        let link = dir.path().join("link.toml");
        std::os::unix::fs::symlink(&file, &link).unwrap();
        assert!(read_bounded(&link, 64).is_ok());
        // A directory.
        let e = read_bounded(dir.path(), 64).unwrap_err();
        assert!(e.to_string().contains("directory"), "{e}");
        // Not UTF-8.
        std::fs::write(&file, b"cell = \xff\n").unwrap();
        assert!(read_text_bounded(&file, 64).is_err());
    }
}
