use super::*;

#[test]
fn the_same_name_gives_the_same_counters() {
    let a = link("metrics-test-link");
    a.add_bytes(3, 4);
    let b = link("metrics-test-link");
    assert_eq!(b.bytes(), (3, 4));
    let m = machine("metrics-test-machine");
    m.job_ended(Outcome::Failed, None);
    assert_eq!(machine("metrics-test-machine").ended(Outcome::Failed), 1);
    plc_station_timeout("metrics-test-plc", 7);
    plc_station_timeout("metrics-test-plc", 7);
    assert_eq!(plc_station_timeouts("metrics-test-plc", 7), 2);
    assert_eq!(plc_station_timeouts("metrics-test-plc", 8), 0);
}

#[test]
fn collection_reads_the_counters() {
    let (endpoint, reader) = super::super::prometheus::Exposition::new().unwrap();
    let provider = SdkMeterProvider::builder().with_reader(reader).build();
    let instruments = register(&provider);
    let l = link("collect-link");
    l.add_bytes(10, 20);
    l.add_frames(1, 2);
    l.checksum_error();
    let m = machine("collect-machine");
    m.set_queue_depth(5);
    m.job_ended(Outcome::Completed, Some(Duration::from_millis(1500)));
    m.add_g05_underruns(3);
    plc_station_timeout("collect-plc", 2);
    let text = endpoint.render().unwrap();
    let has = |line: &str| text.lines().any(|l| l.starts_with(line));
    for line in [
        "cellgate_link_io_bytes_total{direction=\"in\",link=\"collect-link\"",
        "cellgate_link_frames_total{direction=\"out\",link=\"collect-link\"",
        "cellgate_link_checksum_errors_total{link=\"collect-link\"",
        "cellgate_jobs_queue_depth{machine=\"collect-machine\"",
        "cellgate_jobs_ended_total{machine=\"collect-machine\",outcome=\"completed\"",
        "cellgate_g05_underruns_total{machine=\"collect-machine\"",
        "cellgate_plc_station_timeouts_total{plc=\"collect-plc\",station=\"2\"",
        "cellgate_job_duration_seconds_count{machine=\"collect-machine\",outcome=\"completed\"",
    ] {
        assert!(has(line), "no {line} in\n{text}");
    }
    let value = |prefix: &str| -> Option<f64> {
        text.lines()
            .find(|l| l.starts_with(prefix))
            .and_then(|l| l.rsplit(' ').next())
            .and_then(|v| v.parse().ok())
    };
    assert_eq!(
        value("cellgate_link_io_bytes_total{direction=\"out\",link=\"collect-link\""),
        Some(20.0)
    );
    assert_eq!(
        value("cellgate_jobs_queue_depth{machine=\"collect-machine\""),
        Some(5.0)
    );
    // Counted after the provider exists, seen at the next collection.
    l.add_bytes(0, 5);
    let text = endpoint.render().unwrap();
    let out = text
        .lines()
        .find(|l| {
            l.starts_with("cellgate_link_io_bytes_total{direction=\"out\",link=\"collect-link\"")
        })
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse::<f64>().ok());
    assert_eq!(out, Some(25.0));
    drop(instruments);
    provider.shutdown().unwrap();
}
