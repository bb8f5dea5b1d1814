//! How long a file posted into the library's folder takes to become a revision, with 1, 100
//! and 10 000 files posted at once (each written under a temporary name and renamed into
//! place, as a CAM post does), for `watch = "auto"` (inotify) and `"poll"`, at the default
//! `settle_ms` (1 s) and `poll_ms` (2 s). The path measured is the gateway's own: the
//! folder's watcher and the library's `take_file`; the bus adds one publish per revision.
//!
//! `cargo bench --bench folder` prints the table; under `cargo test` a short smoke run
//! (1 and 10 files, auto) checks that it runs.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use cellgate::library::folder::{FolderWatch, Followed, Seen};
use cellgate::library::{FolderFile, ProgramLibrary, Taken};
use cellgate_core::config::{ProgramsConfig, Watch};
use cellgate_core::pb;
use tokio_util::sync::CancellationToken;

fn program(i: usize) -> Vec<u8> {
    let mut p = format!("%\nO{i}\n").into_bytes();
    for n in 0..40 {
        p.extend_from_slice(format!("N{n} G01 X{i}.{n} F100\n").as_bytes());
    }
    p.extend_from_slice(b"M30\n%\n");
    p
}

/// Posts `n` files at once into a fresh library folder; answers the latency of each (from its
/// rename into place to its revision), sorted, and the whole run's time.
async fn run(n: usize, watch: Watch) -> (Vec<Duration>, Duration) {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let defaults = ProgramsConfig::default();
    let library = ProgramLibrary::new(dir.path(), defaults.max_size);
    library.create_dir().await.expect("the library opens");
    let stop = CancellationToken::new();
    let lib = library.clone();
    let Followed { mut seen, .. } = FolderWatch {
        dir: dir.path().to_path_buf(),
        watch,
        settle_ms: u64::from(defaults.settle_ms),
        poll: Duration::from_millis(u64::from(defaults.poll_ms)),
        takes: Arc::new(move |f: &std::ffi::OsStr| lib.verdict(f)),
    }
    .spawn(stop.clone());
    // Let the first listing pass, so that the files are new to the watcher.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let started = Instant::now();
    let mut posted = BTreeMap::new();
    for i in 0..n {
        let name = format!("P{i:05}.nc");
        let temp = dir.path().join(format!("{name}.tmp"));
        std::fs::write(&temp, program(i)).expect("written");
        std::fs::rename(&temp, dir.path().join(&name)).expect("renamed");
        posted.insert(name, Instant::now());
    }
    let mut latencies = Vec::with_capacity(n);
    while latencies.len() < n {
        let Some(s) = tokio::time::timeout(Duration::from_secs(120), seen.recv())
            .await
            .expect("every file taken within 2 minutes")
        else {
            break;
        };
        let Seen::Complete { file } = s else { continue };
        let taken = library
            .take_file(FolderFile {
                file: file.clone(),
                by: pb::RequestOrigin::default(),
            })
            .await
            .expect("taken");
        if let (Taken::Revision(_), Some(at)) = (taken, posted.get(&file)) {
            latencies.push(at.elapsed());
        }
    }
    let total = started.elapsed();
    stop.cancel();
    latencies.sort();
    (latencies, total)
}

fn ms(d: Duration) -> String {
    format!("{:.0}", d.as_secs_f64() * 1000.0)
}

#[tokio::main]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let cases: &[(usize, Watch)] = if full {
        &[
            (1, Watch::Auto),
            (100, Watch::Auto),
            (10_000, Watch::Auto),
            (1, Watch::Poll),
            (100, Watch::Poll),
            (10_000, Watch::Poll),
        ]
    } else {
        &[(1, Watch::Auto), (10, Watch::Auto)]
    };
    println!("posted files → revisions (settle_ms 1000, poll_ms 2000)");
    println!("| files | watch | first (ms) | median (ms) | last (ms) | all taken (ms) |");
    println!("|---:|---|---:|---:|---:|---:|");
    for &(n, watch) in cases {
        let (lat, total) = run(n, watch).await;
        assert_eq!(lat.len(), n, "every file became a revision");
        let pick = |q: f64| lat[((lat.len() - 1) as f64 * q) as usize];
        println!(
            "| {n} | {watch:?} | {} | {} | {} | {} |",
            ms(pick(0.0)),
            ms(pick(0.5)),
            ms(pick(1.0)),
            ms(total)
        );
    }
}
