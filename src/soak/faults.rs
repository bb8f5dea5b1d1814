//! What each fault of the schedule does to the cell.

use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::task::JoinSet;

use super::rig::{Family, Rig};
use super::schedule::{Fault, FaultKind};
use crate::client::Client;
use cellgate_core::keys::MachineLeaf;

/// Injects faults; holds what outlives one (a full disk, a slow subscriber) until healed.
pub(crate) struct Injector {
    router: String,
    rng: ChaCha8Rng,
    reloads: u32,
    client: Option<Client>,
    background: JoinSet<()>,
    /// When a full disk has room again, while one is full.
    disk_full_until: Option<tokio::time::Instant>,
}

impl Injector {
    pub(crate) fn new(router: &str, seed: u64) -> Injector {
        Injector {
            router: router.to_string(),
            rng: ChaCha8Rng::seed_from_u64(seed.rotate_left(17)),
            reloads: 0,
            client: None,
            background: JoinSet::new(),
            disk_full_until: None,
        }
    }

    /// A client through the router, opened at its first use.
    async fn client(&mut self) -> Result<&Client, String> {
        if self.client.is_none() {
            let options = crate::client::ConnectOptions {
                endpoint: self.router.clone(),
                cell: Some("soak".to_string()),
                timeout: Duration::from_secs(10),
                ..Default::default()
            };
            self.client = Some(Client::connect(&options).await.map_err(|e| e.to_string())?);
        }
        self.client.as_ref().ok_or_else(|| "no client".to_string())
    }

    /// Does `f` to `rig`; why it could not, if it could not.
    pub(crate) async fn inject(&mut self, rig: &mut Rig, f: &Fault) -> Result<(), String> {
        let pick = f.pick as usize;
        let any = rig.machines.get(pick % rig.machines.len().max(1)).cloned();
        let checked: Vec<usize> = (0..rig.machines.len())
            .filter(|&i| rig.machines[i].family.checked())
            .collect();
        let checked = checked.get(pick % checked.len().max(1)).copied();
        match f.kind {
            FaultKind::LineCut => {
                rig.proxies
                    .get(pick % rig.proxies.len().max(1))
                    .ok_or("no line")?
                    .cut();
            }
            FaultKind::DeviceServerRestart => {
                let family = Family::ALL[pick % Family::ALL.len()];
                rig.restart_boards(family, Duration::from_secs(1))
                    .await
                    .map_err(|e| e.to_string())?;
            }
            FaultKind::ChecksumError => {
                rig.proxies[checked.ok_or("no A-family line")?].corrupt_next();
            }
            FaultKind::DroppedByte => {
                rig.proxies[checked.ok_or("no A-family line")?].drop_next();
            }
            FaultKind::CncAlarm => {
                let m = any.ok_or("no machine")?;
                if !rig.operator(&m, "alarm").await {
                    return Err("its board process takes no command".to_string());
                }
                tokio::time::sleep(Duration::from_secs(3)).await;
                rig.operator(&m, "reset").await;
            }
            FaultKind::CncReset => {
                let m = any.ok_or("no machine")?;
                if !rig.operator(&m, "reset").await {
                    return Err("its board process takes no command".to_string());
                }
            }
            FaultKind::GatewayKill => {
                // Not while the disk is full: the history holds its records in memory then,
                // and a kill -9 loses them (docs/history.md, "Durability"); the soak checks
                // what the gateway promises, so the kill waits until the disk has room.
                if let Some(until) = self.disk_full_until.take() {
                    tokio::time::sleep_until(until + Duration::from_secs(3)).await;
                }
                rig.kill_gateway().await;
                tokio::time::sleep(Duration::from_secs(2)).await;
                rig.start_gateway().map_err(|e| e.to_string())?;
            }
            FaultKind::Reload => {
                // Remove the spare, add it back, change its Tp: in turn.
                match self.reloads % 3 {
                    0 => rig.spare_present = false,
                    1 => rig.spare_present = true,
                    _ => rig.spare_tp = if rig.spare_tp == 5 { 6 } else { 5 },
                }
                self.reloads += 1;
                rig.write_cell_file().map_err(|e| e.to_string())?;
                let client = self.client().await?;
                client.reload(false).await.map_err(|e| e.to_string())?;
            }
            FaultKind::RouterRestart => {
                rig.stop_router().await;
                tokio::time::sleep(Duration::from_secs(2)).await;
                rig.start_router().map_err(|e| e.to_string())?;
            }
            FaultKind::DiskFull => {
                if !rig.tmpfs {
                    return Err("no tmpfs could be mounted (not root?)".to_string());
                }
                let fill = rig.data.join("fill");
                tokio::task::spawn_blocking({
                    let fill = fill.clone();
                    move || fill_disk(&fill)
                })
                .await
                .map_err(|e| e.to_string())?;
                self.disk_full_until = Some(tokio::time::Instant::now() + Duration::from_secs(15));
                self.background.spawn(async move {
                    tokio::time::sleep(Duration::from_secs(15)).await;
                    let _ = tokio::fs::remove_file(&fill).await;
                });
            }
            FaultKind::SlowSubscriber => {
                let client = self.client().await?;
                let everything = client.keys().all();
                // A queue of 16 samples nobody reads for twenty seconds.
                let sub = client
                    .session()
                    .declare_subscriber(everything)
                    .with(zenoh::handlers::FifoChannel::new(16))
                    .await
                    .map_err(|e| e.to_string())?;
                self.background.spawn(async move {
                    tokio::time::sleep(Duration::from_secs(20)).await;
                    drop(sub);
                });
            }
            FaultKind::HostileBurst => {
                let names: Vec<String> = rig.machines.iter().map(|m| m.name.clone()).collect();
                let mut payloads = Vec::new();
                for _ in 0..60 {
                    let len = self.rng.random_range(0..4096);
                    let mut p = vec![0u8; len];
                    self.rng.fill(&mut p[..]);
                    payloads.push(p);
                }
                let client = self.client().await?;
                hostile_burst(client, &names, payloads).await;
            }
        }
        Ok(())
    }

    /// Ends what faults left standing: the disk emptied, slow subscribers gone.
    pub(crate) async fn heal(&mut self, _rig: &mut Rig) {
        while self.background.join_next().await.is_some() {}
        if let Some(c) = self.client.take() {
            c.close().await;
        }
    }
}

/// Writes `path` until the filesystem is full.
fn fill_disk(path: &std::path::Path) {
    use std::io::Write;
    let Ok(mut f) = std::fs::File::create(path) else {
        return;
    };
    let chunk = vec![0u8; 1 << 20];
    while f.write_all(&chunk).is_ok() {}
    // The last partial chunk too, so that not a block is left.
    let mut small = vec![0u8; 4096];
    while f.write(&small).is_ok_and(|n| n > 0) {
        small.truncate(4096);
    }
    let _ = f.sync_all();
}

/// Two hundred requests at once, none of them well-formed: garbage on every write key, reads
/// of everything.
async fn hostile_burst(client: &Client, machines: &[String], payloads: Vec<Vec<u8>>) {
    let session = client.session();
    let keys = client.keys();
    let mut gets = Vec::new();
    for (i, p) in payloads.into_iter().enumerate() {
        let m = &machines[i % machines.len().max(1)];
        let key = match i % 4 {
            0 => keys.leaf(m, MachineLeaf::Submit),
            1 => keys.leaf(m, MachineLeaf::Do),
            2 => keys.program_write(&format!("HOSTILE{}", i % 3)),
            _ => keys.all(),
        };
        if i % 4 == 1 {
            let _ = session.put(key.clone(), p.clone()).await;
        }
        gets.push(async move {
            let Ok(replies) = session
                .get(key)
                .payload(p)
                .timeout(Duration::from_secs(5))
                .await
            else {
                return;
            };
            let drain = async { while replies.recv_async().await.is_ok() {} };
            let _ = tokio::time::timeout(Duration::from_secs(10), drain).await;
        });
    }
    futures::future::join_all(gets).await;
}
