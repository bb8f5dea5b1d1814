//! The job manager against a stand-in link, in paused tokio time. Test code only: `mod.rs`
//! declares this module under #[cfg(test)].

use std::sync::{Arc, Mutex};

use bytes::Bytes;
use tokio::io::AsyncReadExt;
use tokio::sync::Semaphore;

use super::*;
use crate::jobs::journal::Journal;
use crate::link::driver::JobFailure;
use cellgate_core::codes::BusCode as _;
use cellgate_core::config::CellConfig;
use cellgate_core::fanuc::Protocol;
use cellgate_core::fanuc::error::{AbortReason, LinkAlarm};

/// What the stand-in link was told, in order.
type Log = Arc<Mutex<Vec<String>>>;

/// A link that takes each job once the test releases it, then "sends" it `chunk` bytes every
/// `pace`, reporting progress per chunk; `Cancel` is honoured between chunks.
struct StandIn {
    commands: mpsc::Receiver<LinkCommand>,
    events: fanout::Sender<LinkEvent>,
    log: Log,
    release: Arc<Semaphore>,
    chunk: usize,
    pace: Duration,
    /// Jobs queued while another one was being sent.
    pending: std::collections::VecDeque<ProgramJob>,
    /// The job being sent, and the end events sent, as a link reports them (`Jobs`).
    active: Option<JobId>,
    ends: Vec<LinkEvent>,
    /// Before a job's end, floods the event channel past its capacity: the end finds no
    /// room, the manager misses it and must ask.
    flood_before_end: Arc<std::sync::atomic::AtomicBool>,
    /// Answers `Jobs` as a link that has forgotten its ends.
    forget_ends: Arc<std::sync::atomic::AtomicBool>,
}

impl StandIn {
    fn emit(&mut self, e: LinkEvent) {
        let end = matches!(
            e,
            LinkEvent::JobDone { .. } | LinkEvent::JobCancelled { .. }
        );
        if end {
            self.ends.push(e.clone());
            self.active = None;
        }
        if end
            && self
                .flood_before_end
                .load(std::sync::atomic::Ordering::SeqCst)
        {
            for _ in 0..2000 {
                let _ = self.events.send(LinkEvent::Progress {
                    job: 999_999,
                    acked: 0,
                    sent: 0,
                    total: None,
                    block: None,
                });
            }
        }
        let _ = self.events.send(e);
    }

    fn other(&mut self, cmd: LinkCommand) {
        match cmd {
            LinkCommand::Queue(job) => self.pending.push_back(job),
            LinkCommand::Jobs(reply) => {
                let forget = self.forget_ends.load(std::sync::atomic::Ordering::SeqCst);
                let _ = reply.send(crate::link::driver::LinkJobs {
                    active: self.active,
                    queued: self.pending.iter().map(|j| j.id).collect(),
                    recent_ends: if forget {
                        Vec::new()
                    } else {
                        self.ends.clone()
                    },
                });
            }
            other => self.log.lock().unwrap().push(format!("{other:?}")),
        }
    }

    async fn run(mut self) {
        loop {
            if let Some(job) = self.pending.pop_front() {
                self.job(job).await;
                continue;
            }
            match self.commands.recv().await {
                Some(LinkCommand::Queue(job)) => self.job(job).await,
                Some(other) => self.other(other),
                None => return,
            }
        }
    }

    async fn job(&mut self, job: ProgramJob) {
        self.log
            .lock()
            .unwrap()
            .push(format!("queue {} {}", job.id, job.name));
        self.emit(LinkEvent::JobQueued {
            job: job.id,
            position: 0,
        });
        let release = self.release.clone();
        loop {
            tokio::select! {
                permit = release.acquire() => {
                    permit.unwrap().forget();
                    break;
                }
                cmd = self.commands.recv() => match cmd {
                    Some(LinkCommand::Cancel(id)) if id == job.id => {
                        self.emit(LinkEvent::JobCancelled { job: id, offset: 0, sent: 0 });
                        return;
                    }
                    Some(other) => self.other(other),
                    None => return,
                },
            }
        }
        self.active = Some(job.id);
        self.emit(LinkEvent::JobStarted { job: job.id });
        let mut sent = 0u64;
        let mut data = Vec::new();
        let mut fed = cellgate_core::program::fed::FedBlocks::new();
        let mut buf = vec![0u8; self.chunk];
        let JobSource::Program(mut source) = job.source else {
            panic!("the job manager hands programs from the journal");
        };
        loop {
            let n = source.read(&mut buf).await.unwrap();
            if n == 0 {
                break;
            }
            sent += n as u64;
            data.extend_from_slice(&buf[..n]);
            fed.push(&buf[..n]);
            self.emit(LinkEvent::Progress {
                job: job.id,
                acked: sent,
                sent,
                total: job.size,
                block: fed.acked(sent),
            });
            tokio::select! {
                () = tokio::time::sleep(self.pace) => {}
                cmd = self.commands.recv() => match cmd {
                    Some(LinkCommand::Cancel(id)) if id == job.id => {
                        self.log.lock().unwrap().push(format!("cancel {id} at {sent}"));
                        self.emit(LinkEvent::JobCancelled { job: id, offset: sent, sent });
                        return;
                    }
                    Some(other) => self.other(other),
                    None => return,
                },
            }
        }
        self.log.lock().unwrap().push(format!(
            "done {} {}",
            job.id,
            String::from_utf8_lossy(&data)
        ));
        self.emit(LinkEvent::JobDone {
            job: job.id,
            bytes: sent,
            confirmation: Confirmation::Acknowledged,
            block: fed.acked(sent),
        });
    }
}

struct Rig {
    jobs: JobsHandle,
    events: fanout::Receiver<Arc<pb::JobEvent>>,
    link_events: fanout::Sender<LinkEvent>,
    log: Log,
    release: Arc<Semaphore>,
    library: ProgramLibrary,
    dir: Arc<tempfile::TempDir>,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
    protocol: Protocol,
    chunk: usize,
    pace: Duration,
    flood_before_end: Arc<std::sync::atomic::AtomicBool>,
    forget_ends: Arc<std::sync::atomic::AtomicBool>,
}

fn rig(protocol: Protocol, chunk: usize, pace: Duration) -> Rig {
    rig_in(
        Arc::new(tempfile::tempdir().unwrap()),
        protocol,
        chunk,
        pace,
    )
}

/// A job manager on a stand-in link, its library in `dir` and its journal in
/// `dir/.journal`, restoring whatever that journal holds.
fn rig_in(dir: Arc<tempfile::TempDir>, protocol: Protocol, chunk: usize, pace: Duration) -> Rig {
    let mut machine = CellConfig::embedded_default().machines[0].clone();
    machine.name = "m1".to_string();
    machine.protocol = protocol;
    machine.packet_n = None;
    let (cmd_tx, cmd_rx) = mpsc::channel(64);
    let (ev_tx, _) = fanout::channel(1024);
    let log = Log::default();
    let release = Arc::new(Semaphore::new(0));
    let flood_before_end = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let forget_ends = Arc::new(std::sync::atomic::AtomicBool::new(false));
    tokio::spawn(
        StandIn {
            commands: cmd_rx,
            events: ev_tx.clone(),
            log: log.clone(),
            release: release.clone(),
            chunk,
            pace,
            pending: Default::default(),
            active: None,
            ends: Vec::new(),
            flood_before_end: flood_before_end.clone(),
            forget_ends: forget_ends.clone(),
        }
        .run(),
    );
    let link = LinkHandle::from_channels("m1", cmd_tx, ev_tx.clone());
    let library = ProgramLibrary::new(dir.path(), 1 << 20);
    let journal = Journal::open(&dir.path().join(".journal")).unwrap();
    let mut restored = journal.restore().unwrap();
    let shutdown = CancellationToken::new();
    let settings = JobsSettings {
        rules: machine.program_rules(library.max_size()),
        library: library.clone(),
        journal,
        restored: restored.jobs.remove("m1").unwrap_or_default(),
        keep: KEEP_ENDED,
        accept: Default::default(),
    };
    let (jobs, task, events) = spawn(&machine.name, settings, link, shutdown.clone());
    Rig {
        jobs,
        events,
        link_events: ev_tx,
        log,
        release,
        library,
        dir,
        shutdown,
        task,
        protocol,
        chunk,
        pace,
        flood_before_end,
        forget_ends,
    }
}

impl Rig {
    /// Stops the manager as a gateway shutting down does, and starts a new one on the same
    /// journal and library (a fresh stand-in link).
    async fn restart(self) -> Rig {
        let Rig {
            jobs,
            events,
            shutdown,
            task,
            dir,
            protocol,
            chunk,
            pace,
            ..
        } = self;
        shutdown.cancel();
        task.await.unwrap();
        // The journal closes with its last handle.
        drop((jobs, events));
        rig_in(dir, protocol, chunk, pace)
    }
}

fn inline(program: &'static [u8], priority: i32) -> JobSubmission {
    JobSubmission {
        input: ProgramInput::Inline(Bytes::from_static(program)),
        priority,
        ..JobSubmission::default()
    }
}

/// The next event, within a (virtual) minute.
async fn next(rx: &mut fanout::Receiver<Arc<pb::JobEvent>>) -> pb::JobEvent {
    let e = tokio::time::timeout(Duration::from_secs(60), rx.recv())
        .await
        .expect("no job event")
        .unwrap();
    Arc::unwrap_or_clone(e)
}

/// Events until the job `id` ends, inclusive.
async fn until_end(rx: &mut fanout::Receiver<Arc<pb::JobEvent>>, id: &str) -> Vec<pb::JobEvent> {
    let mut seen = Vec::new();
    loop {
        let e = next(rx).await;
        let end = e.job_id == id
            && matches!(
                e.kind,
                Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
            );
        seen.push(e);
        if end {
            return seen;
        }
    }
}

fn kind_name(e: &pb::JobEvent) -> &'static str {
    match e.kind {
        Some(Kind::Queued(_)) => "queued",
        Some(Kind::Started(_)) => "started",
        Some(Kind::Progress(_)) => "progress",
        Some(Kind::Completed(_)) => "completed",
        Some(Kind::Failed(_)) => "failed",
        Some(Kind::Cancelled(_)) => "cancelled",
        None => "none",
    }
}

#[tokio::test(start_paused = true)]
async fn a_job_runs_through_queued_started_completed() {
    let mut r = rig(Protocol::A, 4, Duration::from_millis(1));
    let accepted = r.jobs.submit(inline(b"%\nO12\nG00X0\n%", 0)).await.unwrap();
    assert_eq!(accepted.queue_position, 0);
    assert!(accepted.job_id.starts_with("m1-"), "{}", accepted.job_id);
    assert!(accepted.job_id.ends_with("-1"), "{}", accepted.job_id);
    r.release.add_permits(1);
    let events = until_end(&mut r.events, &accepted.job_id).await;
    let kinds: Vec<_> = events.iter().map(kind_name).collect();
    assert_eq!(kinds.first(), Some(&"queued"));
    assert_eq!(kinds.get(1), Some(&"started"));
    assert_eq!(kinds.last(), Some(&"completed"));
    match &events.last().unwrap().kind {
        Some(Kind::Completed(c)) => assert_eq!(c.bytes_sent, 13),
        other => panic!("{other:?}"),
    }
    // The size is known from acceptance: a job that ends before it starts keeps it too.
    match &events[0].kind {
        Some(Kind::Queued(q)) => assert_eq!(q.bytes_total, Some(13)),
        other => panic!("{other:?}"),
    }
    assert!(events.iter().all(|e| e.machine == "m1"));
    let log = r.log.lock().unwrap().clone();
    assert_eq!(
        log,
        [
            "queue 1 O12".to_string(),
            "done 1 %\nO12\nG00X0\n%".to_string()
        ]
    );
    let snap = r.jobs.snapshot().borrow().clone();
    assert_eq!(snap.active, None);
    assert_eq!(snap.jobs_completed, 1);
    assert_eq!(snap.nc_bytes_sent, 13);
}

#[tokio::test(start_paused = true)]
async fn jobs_run_by_priority_then_arrival_one_at_a_time() {
    let mut r = rig(Protocol::A, 64, Duration::from_millis(1));
    let a = r.jobs.submit(inline(b"%\nO1\n%", 0)).await.unwrap();
    let b = r.jobs.submit(inline(b"%\nO2\n%", 0)).await.unwrap();
    let c = r.jobs.submit(inline(b"%\nO3\n%", 5)).await.unwrap();
    let d = r.jobs.submit(inline(b"%\nO4\n%", 0)).await.unwrap();
    // a is on the link already; c jumps ahead of b and d.
    assert_eq!(
        [b.queue_position, c.queue_position, d.queue_position],
        [0, 0, 2]
    );
    let q = r.jobs.queue().await.unwrap();
    assert_eq!(q.active.unwrap().job_id, a.job_id);
    let waiting: Vec<_> = q.waiting.iter().map(|j| j.name.as_str()).collect();
    assert_eq!(waiting, ["O3", "O2", "O4"]);
    // Only one job is ever on the link.
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(r.log.lock().unwrap().len(), 1);
    r.release.add_permits(4);
    until_end(&mut r.events, &d.job_id).await;
    let queued: Vec<String> = r
        .log
        .lock()
        .unwrap()
        .iter()
        .filter(|l| l.starts_with("queue"))
        .cloned()
        .collect();
    assert_eq!(
        queued,
        ["queue 1 O1", "queue 2 O3", "queue 3 O2", "queue 4 O4"]
    );
}

#[tokio::test(start_paused = true)]
async fn cancelling_a_waiting_job_drops_it_and_an_active_one_asks_the_link() {
    let mut r = rig(Protocol::A, 2, Duration::from_millis(100));
    let a = r.jobs.submit(inline(b"%\nO1\nG01X1\n%", 0)).await.unwrap();
    let b = r.jobs.submit(inline(b"%\nO2\n%", 0)).await.unwrap();
    assert_eq!(
        r.jobs.cancel(&b.job_id).await.unwrap(),
        CancelOutcome::Dropped
    );
    r.release.add_permits(1);
    // Let a start and send a little.
    loop {
        let e = next(&mut r.events).await;
        if e.job_id == a.job_id && kind_name(&e) == "started" {
            break;
        }
    }
    tokio::time::sleep(Duration::from_millis(150)).await;
    assert_eq!(
        r.jobs.cancel(&a.job_id).await.unwrap(),
        CancelOutcome::Cancelling
    );
    let events = until_end(&mut r.events, &a.job_id).await;
    match &events.last().unwrap().kind {
        Some(Kind::Cancelled(c)) => {
            assert_eq!(c.by, "request");
            assert!(c.byte_offset > 0 && c.byte_offset < 14, "{}", c.byte_offset);
        }
        other => panic!("{other:?}"),
    }
    assert!(matches!(
        r.jobs.cancel(&a.job_id).await,
        Err(JobError::UnknownJob { .. })
    ));
    let log = r.log.lock().unwrap().clone();
    assert!(
        !log.iter().any(|l| l.contains("O2")),
        "b reached the link: {log:?}"
    );
    assert!(log.iter().any(|l| l.starts_with("cancel 1 at")), "{log:?}");
}

#[tokio::test(start_paused = true)]
async fn progress_is_at_most_every_250_ms_and_at_whole_percents() {
    // 10 000 bytes, 10 bytes every 5 ms: the link reports every 0.1 %, for 5 s.
    let mut r = rig(Protocol::A, 10, Duration::from_millis(5));
    let mut program = b"%\nO1\n".to_vec();
    while program.len() < 9_999 {
        program.push(b'G');
    }
    program.push(b'%');
    let program: &'static [u8] = Box::leak(program.into_boxed_slice());
    let a = r.jobs.submit(inline(program, 0)).await.unwrap();
    r.release.add_permits(1);
    let events = until_end(&mut r.events, &a.job_id).await;
    let mut last: Option<(u64, tokio::time::Instant)> = None;
    let mut count = 0;
    let started = tokio::time::Instant::now();
    for e in &events {
        if let Some(Kind::Progress(p)) = &e.kind {
            count += 1;
            assert_eq!(p.bytes_total, Some(10_000));
            assert!(p.rate_bps > 0);
            if let Some((sent, _)) = last {
                assert!(
                    p.bytes_sent * 100 / 10_000 > sent * 100 / 10_000,
                    "{} after {sent}: not a further whole percent",
                    p.bytes_sent
                );
            }
            last = Some((p.bytes_sent, started));
        }
    }
    // 5 s of sending at one event per 250 ms at most.
    assert!((10..=21).contains(&count), "{count} progress events");
    // The rate is the stand-in's 2000 bytes/s.
    let rates: Vec<u64> = events
        .iter()
        .filter_map(|e| match &e.kind {
            Some(Kind::Progress(p)) => Some(p.rate_bps),
            _ => None,
        })
        .collect();
    assert!(
        rates.iter().skip(1).all(|&r| (1500..=2500).contains(&r)),
        "{rates:?}"
    );
}

#[test]
fn the_shaper_keeps_both_rules() {
    let t0 = tokio::time::Instant::now();
    let ms = |n| t0 + Duration::from_millis(n);
    let mut s = ProgressShaper::new(t0, Some(1000));
    assert_eq!(s.offer(ms(100), 500, 500), None, "too soon");
    assert_eq!(s.offer(ms(250), 505, 505), Some(2020));
    assert_eq!(s.offer(ms(600), 509, 509), None, "same whole percent");
    assert_eq!(s.offer(ms(600), 515, 515), Some(28));
    assert_eq!(s.offer(ms(700), 900, 900), None, "too soon");
    // Either figure crossing a whole percent counts: the sent one runs ahead of the
    // acknowledged one in Protocol B.
    assert_eq!(s.offer(ms(900), 515, 600), Some(283));
    assert_eq!(s.offer(ms(1200), 700, 600), Some(0));
    let mut unknown = ProgressShaper::new(t0, None);
    assert_eq!(unknown.offer(ms(300), 1, 1), Some(3));
    assert_eq!(unknown.offer(ms(600), 1, 1), None, "no further byte");
}

#[tokio::test(start_paused = true)]
async fn bad_programs_are_refused_and_nothing_reaches_the_link() {
    let r = rig(Protocol::B, 64, Duration::from_millis(1));
    let cases: [(&'static [u8], bool, pb::ErrorCode, &str); 4] = [
        (b"", false, pb::ErrorCode::InvalidRequest, "empty"),
        (b"%\nO1\n", false, pb::ErrorCode::InvalidRequest, "EOR"),
        (
            b"%\nO1\x13\n%",
            false,
            pb::ErrorCode::InvalidRequest,
            "DC3 (13h)",
        ),
        (
            b"%\nO1\xC1\n%",
            true,
            pb::ErrorCode::InvalidRequest,
            "bit 7",
        ),
    ];
    for (program, append, code, words) in cases {
        let mut s = inline(program, 0);
        s.append_eor = append;
        let e = r.jobs.submit(s).await.unwrap_err();
        assert_eq!(e.code(), code, "{e}");
        assert!(e.to_string().contains(words), "{e}");
        assert!(e.to_string().contains("machine m1"), "{e}");
    }
    let missing = JobSubmission {
        input: ProgramInput::Library("nope".to_string()),
        ..JobSubmission::default()
    };
    let e = r.jobs.submit(missing).await.unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::NotFound);
    tokio::time::sleep(Duration::from_millis(10)).await;
    assert!(r.log.lock().unwrap().is_empty());
    assert!(r.jobs.queue().await.unwrap().waiting.is_empty());
    // The library source works once the program is there.
    r.library.store("ok", b"%\nO5\n%").await.unwrap();
    let ok = JobSubmission {
        input: ProgramInput::Library("ok".to_string()),
        name: "from library".to_string(),
        ..JobSubmission::default()
    };
    r.jobs.submit(ok).await.unwrap();
    tokio::time::sleep(Duration::from_millis(10)).await;
    assert_eq!(r.log.lock().unwrap().as_slice(), ["queue 1 from library"]);
}

#[tokio::test(start_paused = true)]
async fn a_full_queue_refuses_more() {
    let r = rig(Protocol::A, 64, Duration::from_millis(1));
    // The first job goes to the link, MAX_WAITING wait.
    for _ in 0..=MAX_WAITING {
        r.jobs.submit(inline(b"%\nO1\n%", 0)).await.unwrap();
    }
    let e = r.jobs.submit(inline(b"%\nO1\n%", 0)).await.unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::QueueFull);
    assert_eq!(r.jobs.snapshot().borrow().waiting, MAX_WAITING);
}

#[tokio::test(start_paused = true)]
async fn link_alarms_and_resets_end_the_active_job_with_their_reason() {
    let mut r = rig(Protocol::A, 2, Duration::from_millis(100));
    let a = r.jobs.submit(inline(b"%\nO1\nG01X1\n%", 0)).await.unwrap();
    r.release.add_permits(1);
    loop {
        if kind_name(&next(&mut r.events).await) == "started" {
            break;
        }
    }
    let retry_over = LinkAlarm::RetryOver { count: 4, ne: 3 };
    let _ = r.link_events.send(LinkEvent::Alarm(retry_over.clone()));
    let failure = JobFailure::Aborted(AbortReason::Link(retry_over));
    let _ = r.link_events.send(LinkEvent::JobFailed {
        job: 1,
        offset: 4,
        sent: 6,
        reason: failure.clone(),
    });
    let events = until_end(&mut r.events, &a.job_id).await;
    match &events.last().unwrap().kind {
        Some(Kind::Failed(f)) => {
            assert_eq!(f.alarm_number, "SR0945");
            assert_eq!(f.byte_offset, 4);
            assert_eq!(f.code(), pb::ErrorCode::LinkFailed);
            assert_eq!(f.reason, failure.to_string());
            assert_eq!(f.bytes_on_line, 6);
            // Four bytes of "%\nO1\nG01X1\n%" acknowledged: the first block not whole is line 2.
            let next = f.next_block.as_ref().unwrap();
            assert_eq!((next.line, next.byte_offset), (2, 2));
        }
        other => panic!("{other:?}"),
    }

    let b = r.jobs.submit(inline(b"%\nO2\nG01X1\n%", 0)).await.unwrap();
    r.release.add_permits(1);
    loop {
        let e = next(&mut r.events).await;
        if e.job_id == b.job_id && kind_name(&e) == "started" {
            break;
        }
    }
    let _ = r.link_events.send(LinkEvent::CncReset);
    let _ = r.link_events.send(LinkEvent::JobFailed {
        job: 2,
        offset: 2,
        sent: 2,
        reason: JobFailure::Aborted(AbortReason::CncReset),
    });
    let events = until_end(&mut r.events, &b.job_id).await;
    match &events.last().unwrap().kind {
        Some(Kind::Cancelled(c)) => assert_eq!(c.by, "cnc reset"),
        other => panic!("{other:?}"),
    }
    assert_eq!(r.jobs.snapshot().borrow().jobs_failed, 1);
}

#[tokio::test(start_paused = true)]
async fn a_stopped_link_fails_its_jobs_and_refuses_new_ones() {
    let mut r = rig(Protocol::A, 2, Duration::from_millis(100));
    let a = r.jobs.submit(inline(b"%\nO1\n%", 0)).await.unwrap();
    let b = r.jobs.submit(inline(b"%\nO2\n%", 0)).await.unwrap();
    let _ = r.link_events.send(LinkEvent::Stopped {
        error: Some(Arc::new(crate::link::pump::PumpError::Closed)),
    });
    let events = until_end(&mut r.events, &b.job_id).await;
    let failed: Vec<_> = events
        .iter()
        .filter(|e| kind_name(e) == "failed")
        .map(|e| e.job_id.clone())
        .collect();
    assert_eq!(failed, [a.job_id, b.job_id]);
    let e = r.jobs.submit(inline(b"%\nO3\n%", 0)).await.unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::Unavailable);
}

#[tokio::test(start_paused = true)]
async fn a_restart_runs_the_waiting_jobs_with_their_ids_and_fails_the_active_one() {
    let mut r = rig(Protocol::A, 2, Duration::from_millis(100));
    let program = b"%\nO1\nN10 G01 X1\nN20 X2\nN30 X3\n%";
    let a = r.jobs.submit(inline(program, 0)).await.unwrap();
    let waiting: Vec<String> = {
        let mut ids = Vec::new();
        for (p, prio) in [(&b"%\nO2\n%"[..], 0), (b"%\nO3\n%", 5), (b"%\nO4\n%", 0)] {
            ids.push(r.jobs.submit(inline(p, prio)).await.unwrap().job_id);
        }
        ids
    };
    r.release.add_permits(1);
    // a sends and the board acknowledges some of it.
    loop {
        let e = next(&mut r.events).await;
        if let Some(Kind::Progress(p)) = &e.kind
            && e.job_id == a.job_id
            && p.bytes_sent >= 8
        {
            break;
        }
    }
    let mut r = r.restart().await;
    // The active job ends at once, failed at what the board acknowledged, with the block to
    // resume at; it is never reported twice.
    let failed = until_end(&mut r.events, &a.job_id).await;
    let Some(Kind::Failed(f)) = &failed.last().unwrap().kind else {
        panic!("{failed:?}");
    };
    assert!(f.reason.contains("gateway restarted"), "{}", f.reason);
    assert!(f.byte_offset >= 8, "{}", f.byte_offset);
    assert!(f.next_block.is_some());
    // The waiting ones run, in their order (priority first), with their ids.
    let q = r.jobs.queue().await.unwrap();
    let ids: Vec<String> = q
        .active
        .iter()
        .chain(q.waiting.iter())
        .map(|j| j.job_id.clone())
        .collect();
    assert_eq!(
        ids,
        [waiting[1].clone(), waiting[0].clone(), waiting[2].clone()]
    );
    r.release.add_permits(3);
    until_end(&mut r.events, &waiting[2]).await;
    let done: Vec<String> = r
        .log
        .lock()
        .unwrap()
        .iter()
        .filter(|l| l.starts_with("done"))
        .cloned()
        .collect();
    assert_eq!(done.len(), 3, "{done:?}");
    assert!(done[0].contains("O3") && done[1].contains("O2") && done[2].contains("O4"));
    // A get by id after the restart still finds the job's last event.
    assert!(
        r.jobs
            .restored_events()
            .iter()
            .any(|e| e.job_id == a.job_id)
    );
}

#[tokio::test(start_paused = true)]
async fn a_job_that_asked_for_it_resumes_after_a_restart_from_its_next_block() {
    let mut r = rig(Protocol::A, 4, Duration::from_millis(100));
    let program: &'static [u8] = b"%\nO7 (PART)\nG90\nN10 X1\nN20 X2\nN30 X3\nN40 X4\n%";
    let mut s = inline(program, 0);
    s.resume_after_restart = true;
    let a = r.jobs.submit(s).await.unwrap();
    r.release.add_permits(1);
    // Wait until the board acknowledged into block N20.
    let n20 = program.windows(3).position(|w| w == b"N20").unwrap() as u64;
    let acked_before = loop {
        let e = next(&mut r.events).await;
        if let Some(Kind::Progress(p)) = &e.kind
            && p.bytes_sent > n20
        {
            break p.bytes_sent;
        }
    };
    let mut r = r.restart().await;
    let q = r.jobs.queue().await.unwrap();
    assert_eq!(q.active.unwrap().job_id, a.job_id, "queued again, same id");
    r.release.add_permits(1);
    let events = until_end(&mut r.events, &a.job_id).await;
    assert!(matches!(
        events.last().unwrap().kind,
        Some(Kind::Completed(_))
    ));
    let log = r.log.lock().unwrap().clone();
    // The header, then from the block the acknowledgement stopped in: nothing skipped,
    // and no whole block the board acknowledged sent again.
    let sent = log.iter().find(|l| l.starts_with("done")).unwrap();
    let header = "%\nO7 (PART)\nG90\n";
    let acked = usize::try_from(acked_before).unwrap();
    let line_start = program[..acked]
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(0, |i| i + 1);
    let rest = std::str::from_utf8(&program[line_start..]).unwrap();
    assert_eq!(sent, &format!("done 1 {header}{rest}"));
}

#[tokio::test(start_paused = true)]
async fn a_request_id_seen_before_queues_nothing_even_after_a_restart() {
    let r = rig(Protocol::A, 64, Duration::from_millis(1));
    let mut s = inline(b"%\nO1\n%", 0);
    s.request_id = "mes-4711".to_string();
    let first = r.jobs.submit(s.clone()).await.unwrap();
    let again = r.jobs.submit(s.clone()).await.unwrap();
    assert_eq!(again, first);
    assert_eq!(r.jobs.queue().await.unwrap().waiting.len(), 0);
    assert_eq!(
        r.jobs.snapshot().borrow().active,
        Some(first.job_id.clone())
    );
    let r = r.restart().await;
    let again = r.jobs.submit(s.clone()).await.unwrap();
    assert_eq!(again.job_id, first.job_id);
    // A new id is a new job.
    s.request_id = "mes-4712".to_string();
    let other = r.jobs.submit(s).await.unwrap();
    assert_ne!(other.job_id, first.job_id);
    let e = r
        .jobs
        .submit(JobSubmission {
            request_id: "x".repeat(REQUEST_ID_MAX + 1),
            ..inline(b"%\nO1\n%", 0)
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
}

#[tokio::test(start_paused = true)]
async fn a_job_starts_at_a_block_with_the_header_first_and_a_failed_one_resumes() {
    let mut r = rig(Protocol::A, 3, Duration::from_millis(10));
    let program: &'static [u8] = b"%\nO9\nG90 G54\nN10 X1\nN20 X2\nN30 X3\n%";
    r.library.store("O9", program).await.unwrap();
    let from_n20 = JobSubmission {
        input: ProgramInput::Library("O9".to_string()),
        start_at: Some((StartAt::Sequence(20), 0)),
        ..JobSubmission::default()
    };
    let a = r.jobs.submit(from_n20).await.unwrap();
    r.release.add_permits(1);
    until_end(&mut r.events, &a.job_id).await;
    assert_eq!(
        r.log.lock().unwrap()[1],
        "done 1 %\nO9\nG90 G54\nN20 X2\nN30 X3\n%"
    );

    // A job that fails within N20 resumes there.
    let b = r
        .jobs
        .submit(JobSubmission {
            input: ProgramInput::Library("O9".to_string()),
            ..JobSubmission::default()
        })
        .await
        .unwrap();
    r.release.add_permits(1);
    let n20 = program.windows(3).position(|w| w == b"N20").unwrap() as u64;
    loop {
        let e = next(&mut r.events).await;
        if e.job_id == b.job_id && kind_name(&e) == "started" {
            break;
        }
    }
    let _ = r.link_events.send(LinkEvent::JobFailed {
        job: 2,
        offset: n20 + 2,
        sent: n20 + 5,
        reason: JobFailure::Aborted(AbortReason::CncAlarm),
    });
    let events = until_end(&mut r.events, &b.job_id).await;
    let Some(Kind::Failed(f)) = &events.last().unwrap().kind else {
        panic!("{events:?}");
    };
    let next_block = f.next_block.clone().unwrap();
    assert_eq!(
        (
            next_block.line,
            next_block.sequence_number.as_str(),
            next_block.byte_offset
        ),
        (5, "N20", n20)
    );
    let c = r
        .jobs
        .submit(JobSubmission {
            input: ProgramInput::Resume(b.job_id.clone()),
            ..JobSubmission::default()
        })
        .await
        .unwrap();
    r.release.add_permits(2);
    until_end(&mut r.events, &c.job_id).await;
    let log = r.log.lock().unwrap().clone();
    assert_eq!(
        log.last().unwrap(),
        "done 3 %\nO9\nG90 G54\nN20 X2\nN30 X3\n%"
    );
    // A completed job, or one unknown, cannot be resumed.
    for job in [a.job_id.as_str(), "m1-nope-9"] {
        let e = r
            .jobs
            .submit(JobSubmission {
                input: ProgramInput::Resume(job.to_string()),
                ..JobSubmission::default()
            })
            .await
            .unwrap_err();
        assert!(
            matches!(
                e,
                JobError::NotResumable { .. } | JobError::UnknownJob { .. }
            ),
            "{e}"
        );
    }
    let e = r
        .jobs
        .submit(JobSubmission {
            start_at: Some((StartAt::Sequence(99), 0)),
            ..inline(b"%\nO1\nN10 X1\n%", 0)
        })
        .await
        .unwrap_err();
    assert!(e.to_string().contains("no block N99"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn waiting_jobs_hold_no_file_open() {
    let r = rig(Protocol::A, 64, Duration::from_millis(1));
    r.library.store("O1", b"%\nO1\n%").await.unwrap();
    let open_fds = || std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count());
    let before = open_fds();
    for _ in 0..200 {
        r.jobs
            .submit(JobSubmission {
                input: ProgramInput::Library("O1".to_string()),
                ..JobSubmission::default()
            })
            .await
            .unwrap();
    }
    let after = open_fds();
    // One job is on the stand-in link with its file open; 199 wait.
    assert!(
        after <= before + 8,
        "{before} fds before, {after} after 200 jobs"
    );
    assert_eq!(r.jobs.queue().await.unwrap().waiting.len(), 199);
}

/// A manager that falls behind the link's events asks the link where its jobs stand: a job
/// whose end it missed ends as the link reported it, or fails saying its end was lost, but
/// never stays active.
#[tokio::test(start_paused = true)]
async fn a_job_end_lost_in_a_lag_is_asked_for_and_never_left_active() {
    for forget in [false, true] {
        let mut r = rig(Protocol::A, 8, Duration::from_millis(10));
        r.flood_before_end
            .store(true, std::sync::atomic::Ordering::SeqCst);
        r.forget_ends
            .store(forget, std::sync::atomic::Ordering::SeqCst);
        let accepted = r.jobs.submit(inline(b"%\nO1\nG00X0\n%", 0)).await.unwrap();
        r.release.add_permits(1);
        let end = loop {
            let e = next(&mut r.events).await;
            if e.job_id == accepted.job_id
                && matches!(
                    e.kind,
                    Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
                )
            {
                break e;
            }
        };
        match (forget, end.kind) {
            (false, Some(Kind::Completed(_))) => {}
            (true, Some(Kind::Failed(f))) => {
                assert!(f.reason.contains("was lost"), "{}", f.reason);
            }
            (_, other) => panic!("forget = {forget}: ended {other:?}"),
        }
        // Nothing is left active: the queue is empty.
        let queue = r.jobs.queue().await.unwrap();
        assert!(queue.active.is_none(), "{queue:?}");
    }
}

/// Waits until job `id` has started.
async fn until_started(rx: &mut fanout::Receiver<Arc<pb::JobEvent>>, id: &str) {
    loop {
        let e = next(rx).await;
        if e.job_id == id && kind_name(&e) == "started" {
            return;
        }
    }
}

#[tokio::test(start_paused = true)]
async fn held_jobs_let_the_active_one_end_and_wait_for_the_next_manager() {
    let mut r = rig(Protocol::A, 2, Duration::from_millis(50));
    let a = r.jobs.submit(inline(b"%\nO1\nG01X1\n%", 0)).await.unwrap();
    let b = r.jobs.submit(inline(b"%\nO2\n%", 0)).await.unwrap();
    r.release.add_permits(1);
    until_started(&mut r.events, &a.job_id).await;
    r.jobs.hold(Hold::default()).await.unwrap();
    r.release.add_permits(5);
    // The job being sent goes on to its end; the next one is not handed to the link.
    let end = until_end(&mut r.events, &a.job_id).await;
    assert_eq!(kind_name(end.last().unwrap()), "completed");
    tokio::time::sleep(Duration::from_secs(5)).await;
    let snap = r.jobs.snapshot().borrow().clone();
    assert_eq!((snap.active, snap.waiting), (None, 1));
    // A job submitted now waits as well.
    let c = r.jobs.submit(inline(b"%\nO3\n%", 0)).await.unwrap();
    assert!(!r.log.lock().unwrap().iter().any(|l| l.contains("O2")));
    // The restarted link's manager takes the waiting ones from the journal, with their ids,
    // and numbers its own jobs past them.
    let mut r = r.restart().await;
    r.release.add_permits(3);
    until_end(&mut r.events, &c.job_id).await;
    let d = r.jobs.submit(inline(b"%\nO4\n%", 0)).await.unwrap();
    for id in [&a.job_id, &b.job_id, &c.job_id] {
        assert_ne!(&d.job_id, id);
    }
    until_end(&mut r.events, &d.job_id).await;
    let log = r.log.lock().unwrap().clone();
    let order: Vec<&String> = log.iter().filter(|l| l.starts_with("done")).collect();
    assert_eq!(order.len(), 3, "{log:?}");
    assert!(order[0].contains("O2") && order[1].contains("O3") && order[2].contains("O4"));
}

#[tokio::test(start_paused = true)]
async fn a_machine_leaving_the_cell_drops_its_waiting_jobs_and_a_forced_reload_fails_its_job() {
    let mut r = rig(Protocol::A, 2, Duration::from_millis(100));
    let a = r.jobs.submit(inline(b"%\nO1\nG01X1\n%", 0)).await.unwrap();
    let b = r.jobs.submit(inline(b"%\nO2\n%", 0)).await.unwrap();
    r.release.add_permits(1);
    until_started(&mut r.events, &a.job_id).await;
    tokio::time::sleep(Duration::from_millis(250)).await;
    let hold = Hold {
        fail_active: Some("a forced reload removed machine m1".to_string()),
        retire: Some("is leaving the cell".to_string()),
    };
    r.jobs.hold(hold).await.unwrap();
    let ends: Vec<pb::JobEvent> = [next(&mut r.events).await, next(&mut r.events).await].into();
    let by_id = |id: &str| ends.iter().find(|e| e.job_id == id).unwrap().kind.clone();
    let Some(Kind::Cancelled(c)) = by_id(&b.job_id) else {
        panic!("{ends:?}");
    };
    assert_eq!(c.by, "reload");
    let Some(Kind::Failed(f)) = by_id(&a.job_id) else {
        panic!("{ends:?}");
    };
    assert_eq!(f.reason, "a forced reload removed machine m1");
    assert!(f.byte_offset > 0, "{f:?}");
    assert_eq!(r.jobs.snapshot().borrow().active, None);
    let refused = r.jobs.submit(inline(b"%\nO3\n%", 0)).await.unwrap_err();
    assert_eq!(refused.to_string(), "machine m1 is leaving the cell");
    assert_eq!(refused.code(), pb::ErrorCode::Unavailable);
    // Given its entry back before its link stopped, it takes jobs again.
    r.jobs.release().await.unwrap();
    let d = r.jobs.submit(inline(b"%\nO4\n%", 0)).await.unwrap();
    r.release.add_permits(1);
    assert_eq!(
        kind_name(until_end(&mut r.events, &d.job_id).await.last().unwrap()),
        "completed"
    );
}
