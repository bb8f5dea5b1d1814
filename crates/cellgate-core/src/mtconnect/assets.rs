//! The agent's assets (MTConnect Part 4): a program the CNC punched out to the gateway and
//! the gateway stored in its library is a File asset of the machine (its name, size and
//! version, where it lies on the bus, when it came). Bounded: the newest
//! [`ASSET_BUFFER_SIZE`] are kept.

use std::collections::VecDeque;

use sha2::{Digest, Sha256};

use crate::pb;

/// Assets kept at most (`assetBufferSize`).
pub const ASSET_BUFFER_SIZE: usize = 1024;

/// A File asset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileAsset {
    /// Unique in the agent: `CELL.MACHINE.NAME`; a program punched again replaces its asset.
    pub asset_id: String,
    /// The machine's device (index into the model's devices).
    pub device: usize,
    /// When it came: microseconds since the Unix epoch.
    pub time_us: u64,
    /// Its name in the library.
    pub name: String,
    /// Its size in bytes.
    pub size: u64,
    /// The first 16 hex digits of its SHA-256: one per content.
    pub version: String,
    /// Where it lies: its library key on the bus (`P/C/program/NAME`).
    pub location: String,
    /// Whether its text is the library's program of its O-number (Part 4 "state":
    /// PRODUCTION), or differs or has none to compare with (REVISION: the CNC's copy).
    pub same_as_library: bool,
}

impl FileAsset {
    /// The File asset of a punched program stored under its library name; `None` for one
    /// that was not stored (damaged, a remote request, storing off).
    pub fn of_punched(
        p: &pb::PunchedProgram,
        cell: &str,
        device: usize,
        location: String,
        time_us: u64,
    ) -> Option<FileAsset> {
        if p.library_name.is_empty() || p.damaged || p.request.is_some() {
            return None;
        }
        let digest = Sha256::digest(&p.program);
        Some(FileAsset {
            asset_id: format!("{cell}.{}.{}", p.machine, p.library_name),
            device,
            time_us,
            name: p.library_name.clone(),
            size: p.program.len() as u64,
            version: hex::encode(&digest[..8]),
            location,
            same_as_library: p.comparison.as_ref().is_some_and(|c| c.same),
        })
    }

    /// Part 4's file state.
    pub fn state(&self) -> &'static str {
        if self.same_as_library {
            "PRODUCTION"
        } else {
            "REVISION"
        }
    }
}

/// The assets kept, newest last.
#[derive(Debug, Clone, Default)]
pub struct Assets {
    list: VecDeque<FileAsset>,
}

impl Assets {
    /// Keeps `a`, in place of an asset of the same id; the oldest goes past the bound.
    pub fn put(&mut self, a: FileAsset) {
        self.list.retain(|o| o.asset_id != a.asset_id);
        if self.list.len() == ASSET_BUFFER_SIZE {
            self.list.pop_front();
        }
        self.list.push_back(a);
    }

    /// How many are kept.
    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// Whether none is kept.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// The asset `id`.
    pub fn get(&self, id: &str) -> Option<&FileAsset> {
        self.list.iter().find(|a| a.asset_id == id)
    }

    /// Up to `count` assets of `device` (all if `None`), newest first.
    pub fn newest(&self, device: Option<usize>, count: usize) -> Vec<&FileAsset> {
        self.list
            .iter()
            .rev()
            .filter(|a| device.is_none_or(|d| a.device == d))
            .take(count)
            .collect()
    }
}
