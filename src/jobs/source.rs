//! Where a job's program comes from: inline bytes and bytes fetched from a bus key are already
//! in memory; a library file is read in pieces through the core's [`Scanner`], then rewound and
//! kept open for sending, so a 500 MB program is never held whole. The library replaces files
//! by rename, so the open file keeps the bytes that were checked even if the program is stored
//! again meanwhile. The checks themselves are [`cellgate_core::program::scan`]'s.

use std::io::Cursor;
use std::path::Path;

use bytes::Bytes;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncSeekExt};

use super::journal::StartPoint;
use crate::link::driver::ProgramSource;
use cellgate_core::program::blocks::{Block, BlockAt, BlockError, StartAt, StartSearch};
pub use cellgate_core::program::scan::{
    ProgramError, ProgramRules, ScanReport, Scanner, eor_suffix, scan,
};

/// A program as a job request names it.
#[derive(Debug, Clone)]
pub enum ProgramInput {
    /// The program itself.
    Inline(Bytes),
    /// A program of the cell's library, by name.
    Library(String),
    /// The payload fetched from a bus key.
    Fetched { key: String, bytes: Bytes },
    /// The program of an earlier job, by its id, from where that job stopped.
    Resume(String),
    /// A file of the machine's drop folder, complete: copied into the journal as it is.
    File(std::path::PathBuf),
}

impl Default for ProgramInput {
    fn default() -> Self {
        ProgramInput::Inline(Bytes::new())
    }
}

/// Why a program file could not be checked.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ScanFileError {
    #[error(transparent)]
    Program(#[from] ProgramError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// Checks the program file at `path` against `rules`, streaming through it once.
pub async fn scan_file(rules: ProgramRules, path: &Path) -> Result<ScanReport, ScanFileError> {
    let mut file = tokio::fs::File::open(path).await?;
    let mut scanner = Scanner::new(rules);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = file.read(&mut buf).await?;
        if n == 0 {
            break;
        }
        scanner.feed(buf.get(..n).unwrap_or_default())?;
    }
    Ok(scanner.finish()?)
}

/// A program as the journal keeps it: its file, then `suffix` (an appended EOR).
pub async fn open_program(path: &Path, suffix: &[u8]) -> std::io::Result<ProgramSource> {
    let file = tokio::fs::File::open(path).await?;
    Ok(Box::new(file.chain(Cursor::new(suffix.to_vec()))))
}

/// What a job sends of its program: all of it, or its header and the rest from its start
/// block (`start`), streamed in pieces from the file. The file is opened here, when the job
/// starts, not while it waits.
pub async fn open_stream(
    path: &Path,
    suffix: &[u8],
    start: Option<StartPoint>,
) -> std::io::Result<ProgramSource> {
    let file_len = tokio::fs::metadata(path).await?.len();
    let size = file_len + suffix.len() as u64;
    let ranges = match start {
        None => vec![(0, size)],
        Some(s) => vec![(0, s.header_end.min(size)), (s.body_start.min(size), size)],
    };
    let mut stream: ProgramSource = Box::new(tokio::io::empty());
    for (from, to) in ranges {
        let (f_from, f_to) = (from.min(file_len), to.min(file_len));
        if f_to > f_from {
            let mut file = tokio::fs::File::open(path).await?;
            file.seek(std::io::SeekFrom::Start(f_from)).await?;
            stream = Box::new(stream.chain(file.take(f_to - f_from)));
        }
        let (s_from, s_to) = (from.max(file_len) - file_len, to.max(file_len) - file_len);
        let tail = suffix
            .get(usize::try_from(s_from).unwrap_or(usize::MAX)..usize::try_from(s_to).unwrap_or(0))
            .unwrap_or_default();
        if !tail.is_empty() {
            stream = Box::new(stream.chain(Cursor::new(tail.to_vec())));
        }
    }
    Ok(stream)
}

/// [`cellgate_core::program::blocks::find_start`] over a program read in pieces.
pub async fn find_start<R: AsyncRead + Unpin>(
    mut program: R,
    at: StartAt,
    header_lines: u32,
) -> Result<(u64, Block), BlockError> {
    let mut search = StartSearch::new(at, header_lines)?;
    let mut buf = vec![0u8; READ_CHUNK];
    loop {
        let n = read_piece(&mut program, &mut buf).await?;
        if n == 0 {
            return search.finish();
        }
        if let Some(found) = search.feed(buf.get(..n).unwrap_or_default()) {
            return Ok(found);
        }
    }
}

/// [`cellgate_core::program::blocks::block_at`] over a program read in pieces.
pub async fn block_at<R: AsyncRead + Unpin>(
    mut program: R,
    offset: u64,
) -> Result<Option<Block>, BlockError> {
    let mut search = BlockAt::new(offset);
    let mut buf = vec![0u8; READ_CHUNK];
    loop {
        let n = read_piece(&mut program, &mut buf).await?;
        if n == 0 {
            return Ok(search.finish());
        }
        if let Some(block) = search.feed(buf.get(..n).unwrap_or_default()) {
            return Ok(Some(block));
        }
    }
}

const READ_CHUNK: usize = 64 * 1024;

async fn read_piece<R: AsyncRead + Unpin>(r: &mut R, buf: &mut [u8]) -> Result<usize, BlockError> {
    r.read(buf)
        .await
        .map_err(|e| BlockError::Read(e.to_string()))
}

#[cfg(test)]
mod tests;
