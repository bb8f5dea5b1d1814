//! NC program text, sans-IO: what the library keeps, what a job checks and sends, and what a
//! CNC punches out.
//!
//! - [`scan`]: the checks every program passes before it is queued (size, 7-bit, the
//!   protocol's control codes, EOR; §4.1, §6.2, §8.2);
//! - [`blocks`]: blocks, their lines and sequence numbers, where a job starts or resumes;
//! - [`fed`]: the block being fed, the last one the remote buffer acknowledged whole;
//! - [`diff`]: two programs compared block by block (revisions, a punched program against
//!   the library's);
//! - [`folder`]: the DNC folder: which files are programs, and when a file is complete;
//! - [`name`]: program names, safe as a key chunk and a file name;
//! - [`tape`]: punch codes ISO / ASCII / EIA, conversion and recognition (§10 0000#2, #4);
//! - [`punch`]: a punch-out split into programs, named for the library, and remote requests
//!   for a program (§6.1.1 2).
//!
//! The program window a host engine sends from is the protocol's, [`crate::fanuc::program`].

pub mod blocks;
pub mod diff;
pub mod fed;
pub mod folder;
pub mod name;
pub mod punch;
pub mod scan;
pub mod tape;
