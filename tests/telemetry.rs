//! Traces and metrics leaving the gateway: a real OTLP/gRPC receiver on loopback (the
//! collector services generated from the `opentelemetry-proto` definitions, served by tonic)
//! sees a job's span and the counters; the Prometheus endpoint serves the counters after a
//! job. A gateway of the embedded default cell (simulated boards on simulated lines) runs in
//! this process, each test with its own machine name so that their counters stay apart.
//! Real time, loopback, multicast scouting off.

mod common;

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use cellgate::client::{Client, ConnectOptions};
use cellgate::telemetry;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::free_port;
use opentelemetry_proto::tonic::collector::metrics::v1::metrics_service_server::{
    MetricsService, MetricsServiceServer,
};
use opentelemetry_proto::tonic::collector::metrics::v1::{
    ExportMetricsServiceRequest, ExportMetricsServiceResponse,
};
use opentelemetry_proto::tonic::collector::trace::v1::trace_service_server::{
    TraceService, TraceServiceServer,
};
use opentelemetry_proto::tonic::collector::trace::v1::{
    ExportTraceServiceRequest, ExportTraceServiceResponse,
};
use opentelemetry_proto::tonic::common::v1::{AnyValue, KeyValue, any_value};
use opentelemetry_proto::tonic::metrics::v1::{Metric, metric};
use opentelemetry_proto::tonic::trace::v1::Span;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

// ---- an OTLP/gRPC receiver ---------------------------------------------------------------------

/// What the receiver got: every export request, as sent.
#[derive(Default, Clone)]
struct Received {
    traces: Arc<Mutex<Vec<ExportTraceServiceRequest>>>,
    metrics: Arc<Mutex<Vec<ExportMetricsServiceRequest>>>,
}

#[tonic::async_trait]
impl TraceService for Received {
    async fn export(
        &self,
        request: tonic::Request<ExportTraceServiceRequest>,
    ) -> Result<tonic::Response<ExportTraceServiceResponse>, tonic::Status> {
        self.traces.lock().unwrap().push(request.into_inner());
        Ok(tonic::Response::new(ExportTraceServiceResponse::default()))
    }
}

#[tonic::async_trait]
impl MetricsService for Received {
    async fn export(
        &self,
        request: tonic::Request<ExportMetricsServiceRequest>,
    ) -> Result<tonic::Response<ExportMetricsServiceResponse>, tonic::Status> {
        self.metrics.lock().unwrap().push(request.into_inner());
        Ok(tonic::Response::new(ExportMetricsServiceResponse::default()))
    }
}

impl Received {
    fn spans(&self) -> Vec<Span> {
        self.traces
            .lock()
            .unwrap()
            .iter()
            .flat_map(|r| &r.resource_spans)
            .flat_map(|r| &r.scope_spans)
            .flat_map(|s| s.spans.clone())
            .collect()
    }

    fn metrics(&self, name: &str) -> Vec<Metric> {
        self.metrics
            .lock()
            .unwrap()
            .iter()
            .flat_map(|r| &r.resource_metrics)
            .flat_map(|r| &r.scope_metrics)
            .flat_map(|s| s.metrics.clone())
            .filter(|m| m.name == name)
            .collect()
    }

    /// The largest value of counter `name` at a data point with all of `attrs`.
    fn counter(&self, name: &str, attrs: &[(&str, &str)]) -> Option<u64> {
        let mut best = None;
        for m in self.metrics(name) {
            let Some(metric::Data::Sum(sum)) = m.data else {
                continue;
            };
            for p in sum.data_points {
                if attrs.iter().all(|(k, v)| attr(&p.attributes, k) == Some(v)) {
                    let value = match p.value {
                        Some(
                            opentelemetry_proto::tonic::metrics::v1::number_data_point::Value::AsInt(
                                i,
                            ),
                        ) => u64::try_from(i).unwrap_or(0),
                        Some(
                            opentelemetry_proto::tonic::metrics::v1::number_data_point::Value::AsDouble(
                                d,
                            ),
                        ) => d as u64,
                        None => 0,
                    };
                    best = best.max(Some(value));
                }
            }
        }
        best
    }
}

/// The string (or integer, as text) value of attribute `key`.
fn attr<'a>(attrs: &'a [KeyValue], key: &str) -> Option<&'a str> {
    attrs
        .iter()
        .find(|kv| kv.key == key)
        .and_then(|kv| kv.value.as_ref())
        .and_then(|v: &AnyValue| match &v.value {
            Some(any_value::Value::StringValue(s)) => Some(s.as_str()),
            _ => None,
        })
}

fn int_attr(attrs: &[KeyValue], key: &str) -> Option<i64> {
    attrs
        .iter()
        .find(|kv| kv.key == key)
        .and_then(|kv| kv.value.as_ref())
        .and_then(|v| match &v.value {
            Some(any_value::Value::IntValue(i)) => Some(*i),
            _ => None,
        })
}

/// Serves the trace and metrics collector services on a free loopback port.
async fn start_receiver() -> (SocketAddr, Received, tokio::sync::oneshot::Sender<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let received = Received::default();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tonic::transport::Server::builder()
        .add_service(TraceServiceServer::new(received.clone()))
        .add_service(MetricsServiceServer::new(received.clone()));
    tokio::spawn(async move {
        server
            .serve_with_incoming_shutdown(
                tonic::transport::server::TcpIncoming::from(listener),
                async {
                    let _ = stopped.await;
                },
            )
            .await
            .unwrap();
    });
    (addr, received, stop)
}

// ---- a gateway ---------------------------------------------------------------------------------

/// The embedded default cell cut down to its first machine, renamed `machine`, on a free
/// loopback port.
fn cell(name: &str, machine: &str, dir: &std::path::Path) -> (CellConfig, u16) {
    let port = free_port();
    let mut config = CellConfig::embedded_default();
    // Its console would take a fixed port; this test does not look at it.
    config.console = None;
    config.mtconnect = None;
    config.opcua = None;
    config.cell = name.to_string();
    config.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
    config.bus.connect = Vec::new();
    config.bus.multicast_scouting = false;
    config.programs.dir = dir.join("programs");
    config.machines.truncate(1);
    config.machines[0].name = machine.to_string();
    config.telemetry.log_filter = "info".to_string();
    (config, port)
}

struct Running {
    client: Client,
    stop: tokio::sync::oneshot::Sender<()>,
    gateway: tokio::task::JoinHandle<Result<(), cellgate::gateway::GatewayError>>,
}

async fn start_gateway(config: CellConfig, port: u16) -> Running {
    let cell = config.cell.clone();
    let machine = config.machines[0].name.clone();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let gateway = tokio::spawn(cellgate::gateway::run(config, async {
        let _ = stopped.await;
    }));
    let options = ConnectOptions {
        endpoint: format!("tcp/127.0.0.1:{port}"),
        cell: Some(cell),
        ..ConnectOptions::default()
    };
    // The gateway may still be starting.
    let mut client = None;
    for _ in 0..100 {
        match Client::connect(&options).await {
            Ok(c) => {
                client = Some(c);
                break;
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
    let client = client.expect("the gateway never answered");
    // The machine's routes are declared once its token is up.
    common::bus::wait_token(client.session(), &client.keys().machine(&machine), true).await;
    Running {
        client,
        stop,
        gateway,
    }
}

impl Running {
    /// Submits `program` to `machine` and waits for the job's end.
    async fn run_job(&self, machine: &str, program: &[u8]) -> (String, pb::JobEvent) {
        let request = pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(program.to_vec())),
            name: "telemetry test".to_string(),
            ..Default::default()
        };
        let (accepted, mut follower) = self.client.submit(machine, &request).await.unwrap();
        let end = tokio::time::timeout(Duration::from_secs(60), follower.wait_end())
            .await
            .expect("the job did not end within 60 s")
            .unwrap();
        follower.close().await;
        (accepted.job_id, end)
    }

    async fn stop(self) {
        self.client.close().await;
        self.stop.send(()).unwrap();
        tokio::time::timeout(Duration::from_secs(10), self.gateway)
            .await
            .expect("the gateway did not stop within 10 s")
            .unwrap()
            .unwrap();
    }
}

/// `GET path` from the Prometheus endpoint: status line and body.
async fn http_get(addr: SocketAddr, path: &str) -> (String, String) {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(
            format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes(),
        )
        .await
        .unwrap();
    let mut response = String::new();
    tokio::time::timeout(Duration::from_secs(5), stream.read_to_string(&mut response))
        .await
        .expect("no answer within 5 s")
        .unwrap();
    let (head, body) = response.split_once("\r\n\r\n").expect("no header end");
    let status = head.lines().next().unwrap_or_default().to_string();
    (status, body.to_string())
}

/// The value of the sample whose name and labels start with `prefix` (labels in the
/// exporter's order: sorted by name).
fn sample(text: &str, prefix: &str) -> Option<f64> {
    text.lines()
        .find(|l| l.starts_with(prefix))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
}

// ---- the tests ---------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_otlp_receiver_sees_the_jobs_span_and_the_counters() {
    const MACHINE: &str = "otlp-mill";
    let (receiver_addr, received, stop_receiver) = start_receiver().await;
    let dir = tempfile::tempdir().unwrap();
    let (mut config, port) = cell("otlp", MACHINE, dir.path());
    config.telemetry.otlp_endpoint = Some(format!("http://{receiver_addr}"));
    config.telemetry.service_name = "cellgate-otlp-test".to_string();

    // What `cellgate run` does: the global subscriber and both exporters, then the gateway.
    let mut guard = telemetry::init(&config.telemetry).unwrap();
    assert!(guard.exporting());
    assert!(guard.metrics().active());
    assert_eq!(
        guard.metrics().prometheus_addr(),
        None,
        "no endpoint asked for"
    );

    let gateway = start_gateway(config, port).await;
    let program = common::nc_program(1500, 14);
    let (job_id, end) = gateway.run_job(MACHINE, &program).await;
    assert!(
        matches!(end.kind, Some(pb::job_event::Kind::Completed(_))),
        "{end:?}"
    );
    gateway.stop().await;
    // Stopping flushes what is pending: the job's span, the session's, the last metrics.
    guard.shutdown().unwrap();

    let spans = received.spans();
    let job = spans
        .iter()
        .find(|s| s.name == "job" && attr(&s.attributes, "job.id") == Some(job_id.as_str()))
        .unwrap_or_else(|| {
            let names: Vec<_> = spans.iter().map(|s| s.name.as_str()).collect();
            panic!("no span of job {job_id} among {names:?}")
        });
    assert_eq!(attr(&job.attributes, "machine"), Some(MACHINE));
    assert_eq!(attr(&job.attributes, "job.outcome"), Some("completed"));
    assert_eq!(
        int_attr(&job.attributes, "job.bytes"),
        Some(i64::try_from(program.len()).unwrap()),
        "{:?}",
        job.attributes
    );
    let events: Vec<_> = job.events.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(events, ["queued", "started", "ended"], "{job:?}");
    assert!(job.end_time_unix_nano > job.start_time_unix_nano);
    assert!(
        job.parent_span_id.is_empty(),
        "a job is a trace of its own: {job:?}"
    );
    let session = spans
        .iter()
        .find(|s| s.name == "link session" && attr(&s.attributes, "link") == Some(MACHINE))
        .expect("no link session span");
    assert!(
        int_attr(&session.attributes, "bytes_out").unwrap_or(0) >= program.len() as i64,
        "{session:?}"
    );

    let resource_names: Vec<_> = received
        .metrics
        .lock()
        .unwrap()
        .iter()
        .flat_map(|r| &r.resource_metrics)
        .filter_map(|r| r.resource.as_ref())
        .filter_map(|r| attr(&r.attributes, "service.name").map(str::to_string))
        .collect();
    assert!(
        resource_names.iter().any(|n| n == "cellgate-otlp-test"),
        "{resource_names:?}"
    );
    let out = received
        .counter(
            "cellgate.link.io",
            &[("link", MACHINE), ("direction", "out")],
        )
        .expect("no bytes counter for the link");
    assert!(out >= program.len() as u64, "{out} bytes out");
    assert!(
        received
            .counter(
                "cellgate.link.io",
                &[("link", MACHINE), ("direction", "in")]
            )
            .unwrap_or(0)
            > 0
    );
    assert!(
        received
            .counter(
                "cellgate.link.frames",
                &[("link", MACHINE), ("direction", "out")]
            )
            .unwrap_or(0)
            > 0
    );
    assert_eq!(
        received.counter(
            "cellgate.jobs.ended",
            &[("machine", MACHINE), ("outcome", "completed")]
        ),
        Some(1)
    );
    assert_eq!(
        received.counter(
            "cellgate.jobs.ended",
            &[("machine", MACHINE), ("outcome", "failed")]
        ),
        Some(0)
    );
    let durations: u64 = received
        .metrics("cellgate.job.duration")
        .into_iter()
        .filter_map(|m| match m.data {
            Some(metric::Data::Histogram(h)) => Some(h),
            _ => None,
        })
        .flat_map(|h| h.data_points)
        .filter(|p| attr(&p.attributes, "machine") == Some(MACHINE))
        .map(|p| p.count)
        .max()
        .unwrap_or(0);
    assert_eq!(durations, 1, "one job duration recorded");
    let _ = stop_receiver.send(());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_prometheus_endpoint_serves_the_counters_after_a_job() {
    const MACHINE: &str = "prom-mill";
    let dir = tempfile::tempdir().unwrap();
    let (mut config, port) = cell("prom", MACHINE, dir.path());
    config.telemetry.prometheus = Some("127.0.0.1:0".to_string());
    // Only the metrics pipeline: the other test owns this process's global subscriber.
    let mut metrics = telemetry::install_metrics(&config.telemetry, None).unwrap();
    let addr = metrics.prometheus_addr().expect("the endpoint is bound");
    assert!(addr.ip().is_loopback());

    let gateway = start_gateway(config, port).await;
    let completed =
        format!("cellgate_jobs_ended_total{{machine=\"{MACHINE}\",outcome=\"completed\"}}");
    let bytes_out = format!("cellgate_link_io_bytes_total{{direction=\"out\",link=\"{MACHINE}\"}}");
    let (status, before) = http_get(addr, "/metrics").await;
    assert_eq!(status, "HTTP/1.1 200 OK");
    assert_eq!(sample(&before, &completed).unwrap_or(0.0), 0.0, "{before}");

    let program = common::nc_program(1200, 15);
    let (_, end) = gateway.run_job(MACHINE, &program).await;
    assert!(
        matches!(end.kind, Some(pb::job_event::Kind::Completed(_))),
        "{end:?}"
    );
    let (status, after) = http_get(addr, "/metrics").await;
    assert_eq!(status, "HTTP/1.1 200 OK");
    assert_eq!(sample(&after, &completed), Some(1.0), "{after}");
    let out = sample(&after, &bytes_out).unwrap_or(0.0);
    assert!(out >= program.len() as f64, "{out} bytes out:\n{after}");
    assert!(
        after.contains(&format!(
            "cellgate_job_duration_seconds_count{{machine=\"{MACHINE}\",outcome=\"completed\"}} 1"
        )),
        "{after}"
    );
    assert!(
        after.contains(&format!(
            "cellgate_jobs_queue_depth{{machine=\"{MACHINE}\"}} 0"
        )),
        "{after}"
    );
    // Only /metrics is served.
    let (status, _) = http_get(addr, "/").await;
    assert_eq!(status, "HTTP/1.1 404 Not Found");

    gateway.stop().await;
    metrics.shutdown().unwrap();
    // The endpoint closes with the pipeline.
    let mut closed = false;
    for _ in 0..50 {
        if tokio::net::TcpStream::connect(addr).await.is_err() {
            closed = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(
        closed,
        "the endpoint still accepts connections after shutdown"
    );
}

/// The link's counters against what the simulated line carried and what the link reported:
/// bytes as the line counted them, and every retry, checksum error, line error and alarm the
/// link's events showed. A line error before a job, then checksum noise both ways during it.
/// Virtual time, no bus.
#[tokio::test(start_paused = true)]
async fn the_link_counters_follow_the_line_and_the_link_events() {
    use cellgate::link::driver::LinkEvent;
    use cellgate::telemetry::metrics;
    use cellgate::transport::sim::{Dir, Noise};
    use cellgate_core::engine::LineError;
    use cellgate_core::fanuc::error::LinkAlarm;
    use cellgate_core::fanuc::host::LinkState;

    const MACHINE: &str = "counted-a";
    const HOUR: Duration = Duration::from_secs(3600);
    let mut config = common::sim_cell("a", None, 19_200, 960);
    config.machines[0].name = MACHINE.to_string();
    // DATs of Nb - No = 250 bytes, so that a frame fits the noise's guard.
    config.machines[0].nb = Some(300);
    config.machines[0].no = Some(50);
    let (cell, token) = common::start(&config).await;
    let m = cell.machine(MACHINE).unwrap();
    let line = m.line.as_ref().unwrap().clone();
    let mut events = m.link.subscribe();
    let ready = |ev: &LinkEvent| {
        matches!(
            ev,
            LinkEvent::State {
                state: LinkState::Ready
            }
        )
        .then_some(())
    };
    common::next_event(&mut events, HOUR, ready).await;
    assert_eq!(metrics::link(MACHINE).counts().sessions, 1);

    // A framing error from the board: a line alarm, the link re-initialises.
    let mut seen = metrics::LinkCounts::default();
    line.error_next(Dir::DeviceToHost, LineError::Framing);
    common::next_event(&mut events, HOUR, |ev| {
        matches!(ev, LinkEvent::Alarm(LinkAlarm::Line(_))).then_some(())
    })
    .await;
    seen.alarms += 1;
    seen.line_errors += 1;
    common::next_event(&mut events, HOUR, ready).await;

    for (dir, seed) in [(Dir::HostToDevice, 7), (Dir::DeviceToHost, 11)] {
        line.set_noise(
            dir,
            Noise {
                corrupt_ppm: 500,
                drop_ppm: 0,
                guard: 300,
                seed,
            },
        );
    }
    let program = common::nc_program(16 * 1024, 21);
    common::queue(&m.link, 1, program).await;
    let ended = tokio::time::timeout(HOUR, async {
        loop {
            match events.recv().await {
                Ok(LinkEvent::ProtocolError { error, retried }) => {
                    seen.retries += u64::from(retried);
                    seen.checksum_errors += u64::from(error.is_checksum());
                }
                Ok(LinkEvent::Alarm(alarm)) => {
                    seen.alarms += 1;
                    seen.line_errors += u64::from(matches!(
                        alarm,
                        LinkAlarm::Line(_) | LinkAlarm::FrameParity { .. }
                    ));
                }
                Ok(LinkEvent::JobDone { job: 1, .. }) => return true,
                Ok(LinkEvent::JobFailed { job: 1, .. }) => return false,
                Ok(_) => {}
                Err(e) => panic!("link events: {e}"),
            }
        }
    })
    .await
    .expect("the job did not end within an hour");
    assert!(ended, "the job failed under light noise");
    for dir in [Dir::HostToDevice, Dir::DeviceToHost] {
        line.set_noise(dir, Noise::default());
    }
    // Stopping the link counts what it moved last.
    token.cancel();
    cell.join().await;

    let c = metrics::link(MACHINE).counts();
    assert_eq!(c.bytes_out, line.counters(Dir::HostToDevice).written);
    assert_eq!(c.bytes_in, line.counters(Dir::DeviceToHost).delivered);
    assert!(
        seen.checksum_errors > 0 && seen.retries > 0,
        "the noise made no checksum error: {seen:?}"
    );
    assert_eq!(c.checksum_errors, seen.checksum_errors, "{c:?}");
    assert_eq!(c.retries, seen.retries, "{c:?}");
    assert_eq!(c.alarms, seen.alarms, "{c:?}");
    assert_eq!(c.line_errors, seen.line_errors, "{c:?}");
    assert!(
        c.sessions >= 2,
        "up, then up again after the line alarm: {c:?}"
    );
    // Every DAT of the program is a frame out; every SAT, GTD and the like a frame in.
    assert!(c.frames_out > (16 * 1024 / 250) as u64, "{c:?}");
    assert!(c.frames_in > 0, "{c:?}");
}
