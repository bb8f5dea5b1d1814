use super::*;
use cellgate::link::driver::{self, LinkCommand, LinkEvent, LinkHandle, ProgramJob};
use cellgate::sim::{BoardHandle, BoardSnapshot};
use cellgate::transport::LineSettings;
use cellgate::transport::sim::{self, End, SimLine};
use cellgate_core::fanuc::protocol_a::{ProtocolAConfig, ProtocolAHost};
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

/// The gateway's host link and a simulated board on one simulated cable.
struct Cell {
    board: BoardHandle,
    link: LinkHandle,
    line: SimLine,
    events: cellgate::link::fanout::Receiver<LinkEvent>,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<Result<(), std::sync::Arc<cellgate::link::pump::PumpError>>>,
}

impl Cell {
    fn new(protocol: Protocol, packet_n: u8, baud: u32, consume_rate: u32) -> Cell {
        let settings = LineSettings::with_baud(baud);
        let (host_end, board_end, line) = sim::line(settings);
        let board_config = BoardConfig {
            protocol,
            autostart: true,
            consume_rate,
            ..BoardConfig::default()
        };
        let board = BoardHandle::spawn(board_config, board_end).unwrap();
        let host_config = ProtocolAConfig {
            packet_n,
            char_time: settings.char_time(),
            ..ProtocolAConfig::default()
        };
        let host = ProtocolAHost::new(host_config, tokio::time::Instant::now().into_std()).unwrap();
        let shutdown = CancellationToken::new();
        let (link, task) = driver::spawn("m1", host, host_end, shutdown.clone());
        let events = link.subscribe();
        Cell {
            board,
            link,
            line,
            events,
            shutdown,
            task,
        }
    }

    async fn queue(&self, id: u64, prog: &[u8]) {
        self.link
            .send(LinkCommand::Queue(ProgramJob {
                id,
                name: format!("job {id}"),
                size: Some(prog.len() as u64),
                source: cellgate::link::driver::JobSource::program(std::io::Cursor::new(
                    prog.to_vec(),
                )),
                progress_interval: None,
            }))
            .await
            .unwrap();
    }

    /// The job's end as the host saw it: Ok(bytes) or Err(reason).
    async fn job_end(&mut self, id: u64) -> Result<u64, String> {
        loop {
            match self.events.recv().await.unwrap() {
                LinkEvent::JobDone { job, bytes, .. } if job == id => return Ok(bytes),
                LinkEvent::JobFailed { job, reason, .. } if job == id => {
                    return Err(reason.to_string());
                }
                _ => {}
            }
        }
    }

    async fn programs(&self, n: usize) -> BoardSnapshot {
        self.board.wait_for(|s| s.programs.len() >= n).await
    }

    async fn stop(self) {
        self.shutdown.cancel();
        self.task.await.unwrap().ok();
        self.board.shutdown().await.unwrap();
    }
}

async fn download(protocol: Protocol, packet_n: u8, baud: u32, consume_rate: u32) {
    let mut cell = Cell::new(protocol, packet_n, baud, consume_rate);
    let prog = program(2500);
    cell.queue(7, &prog).await;
    assert_eq!(cell.job_end(7).await, Ok(prog.len() as u64));
    let snap = cell.programs(1).await;
    assert_eq!(snap.programs[0].sha256, sha(&prog));
    assert_eq!(snap.programs[0].first_line, "O1234 (SIM)");
    assert!(snap.alarms.is_empty(), "{:?}", snap.alarms);
    assert_eq!(snap.packet_n, packet_n);
    cell.stop().await;
}

#[tokio::test(start_paused = true)]
async fn protocol_a_download_end_to_end() {
    download(Protocol::A, 0, 9600, 2000).await;
}

#[tokio::test(start_paused = true)]
async fn expansion_a_download_end_to_end_with_flow_control() {
    download(Protocol::ExpansionA, 2, 38_400, 1500).await;
}

/// Corrupts one byte from the host once the board holds `after` bytes of NC data.
async fn corrupt_during(protocol: Protocol, packet_n: u8) {
    let mut cell = Cell::new(protocol, packet_n, 19_200, 3000);
    let prog = program(1500);
    cell.queue(1, &prog).await;
    cell.board.wait_for(|s| s.data_received > 8000).await;
    let mut board_events = cell.board.subscribe();
    cell.line.corrupt_next(End::Host.tx(), 0x04);
    assert_eq!(cell.job_end(1).await, Ok(prog.len() as u64));
    let mut retried = false;
    loop {
        match board_events.try_recv() {
            Ok(e) => {
                retried |= matches!(
                    e,
                    BoardEvent::MessageSent(Command::Rty)
                        | BoardEvent::MonitorSent(Monitor::Retransmit(_))
                );
            }
            Err(broadcast::error::TryRecvError::Lagged(_)) => {}
            Err(_) => break,
        }
    }
    assert!(retried, "the board asked for the spoiled data again");
    let snap = cell.programs(1).await;
    assert_eq!(snap.programs[0].sha256, sha(&prog));
    assert!(snap.alarms.is_empty(), "{:?}", snap.alarms);
    assert_eq!(cell.line.counters(End::Host.tx()).corrupted, 1);
    cell.stop().await;
}

#[tokio::test(start_paused = true)]
async fn corrupted_dat_is_retried_end_to_end() {
    corrupt_during(Protocol::A, 0).await;
}

#[tokio::test(start_paused = true)]
async fn corrupted_packet_is_nakked_end_to_end() {
    corrupt_during(Protocol::ExpansionA, 1).await;
}

#[tokio::test(start_paused = true)]
async fn cut_cable_raises_sr0855_and_the_link_comes_back() {
    let mut cell = Cell::new(Protocol::A, 0, 9600, 500);
    let prog = program(1500);
    cell.queue(1, &prog).await;
    cell.board.wait_for(|s| s.data_received > 4000).await;
    cell.line.cut();
    let snap = cell
        .board
        .wait_for(|s| s.link == BoardLinkState::LineDown)
        .await;
    assert_eq!(snap.alarms, vec![CncAlarm::Sr0855DataSetReadyDown]);
    assert!(cell.job_end(1).await.is_err());
    cell.line.restore();
    cell.board
        .wait_for(|s| s.link == BoardLinkState::Ready)
        .await;
    // The CNC resets itself after showing the alarm (autostart) and reads the next job.
    cell.queue(2, &prog).await;
    assert_eq!(cell.job_end(2).await, Ok(prog.len() as u64));
    let snap = cell.programs(1).await;
    assert_eq!(snap.programs[0].sha256, sha(&prog));
    cell.stop().await;
}
