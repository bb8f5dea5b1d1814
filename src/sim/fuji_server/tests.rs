use super::*;
use clap::Parser;

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    args: SimFujiArgs,
}

#[test]
fn options_take_the_cell_file_values() {
    let cli = Cli::try_parse_from([
        "sim",
        "--mode",
        "3",
        "--stations",
        "1,2,31",
        "--parity",
        "odd",
        "--stop-bits",
        "1.5",
        "--data-bits",
        "7",
        "--start-code",
        "set2",
        "--start-codes",
        "0x02,0x05",
        "--end-code",
        "cr-lf",
        "--bcc",
        "set2",
        "--bcc-range",
        "start+text+end",
        "--bcc-calc",
        "crc16",
        "--bcc-code",
        "binary",
        "--no-transposition",
        "--file",
        "30:di:256",
        "--messages",
        "1,7",
    ])
    .unwrap();
    let c = cli.args.micrex_config().unwrap();
    assert_eq!(c.mode, OperationMode::Three);
    assert_eq!(c.stations, vec![1, 2, 31]);
    assert_eq!(c.line.parity, Parity::Odd);
    assert_eq!(c.line.stop_bits, StopBits::OnePointFive);
    assert_eq!(c.line.data_bits, DataBits::Seven);
    assert_eq!(c.frame.start_bytes(), &[0x02, 0x05]);
    assert_eq!(c.frame.end_bytes(), b"\r\n");
    assert!(!c.frame.transposition);
    assert_eq!(c.frame.bcc, cellgate_core::fuji::frame::BccKind::Set2);
    assert_eq!(
        c.frame.bcc_range,
        cellgate_core::fuji::frame::BccRange::StartTextEnd
    );
    assert_eq!(c.frame.bcc_calc, cellgate_core::fuji::frame::BccCalc::Crc16);
    assert_eq!(
        c.frame.bcc_code,
        cellgate_core::fuji::frame::BccCode::Binary
    );
    assert_eq!(c.files, vec![(30, FileType::Di, 256)]);
    assert_eq!(c.messages, vec![1, 7]);
}

/// `--parity-by gateway` (the device server passes 8-bit frames) as the cell file writes it,
/// and refused where a byte has no bit 7 to carry the parity in.
#[tokio::test]
async fn parity_by_gateway_needs_a_7_bit_line_with_parity() {
    let cli =
        Cli::try_parse_from(["sim", "--parity-by", "gateway", "--spoil-parity", "3"]).unwrap();
    assert_eq!(cli.args.parity_by, ParityBy::Gateway);
    assert_eq!(cli.args.spoil_parity, [3]);
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let plan = SessionPlan {
        parity_by: ParityBy::Gateway,
        ..SessionPlan::default()
    };
    let sink: EventSink = Arc::new(|_: &Value| {});
    let e = serve_fuji_on(
        listener,
        cli.args.micrex_config().unwrap(),
        plan,
        sink,
        std::future::ready(()),
    )
    .await
    .unwrap_err();
    assert!(e.to_string().contains("--data-bits 7"), "{e}");
}

#[test]
fn bad_options_are_refused_with_a_reason() {
    for (args, want) in [
        (vec!["--mode", "6"], "1 to 5"),
        (vec!["--bcc-range", "all"], "all"),
        (vec!["--start-codes", "300"], "not a byte"),
        (vec!["--file", "30:XI:5"], "XI"),
        (vec!["--transfer", "5"], "MSGNO:HEXDATA"),
    ] {
        let err = Cli::try_parse_from(std::iter::once("sim").chain(args.iter().copied()))
            .err()
            .unwrap_or_else(|| panic!("{args:?} parsed"));
        assert!(err.to_string().contains(want), "{args:?}: {err}");
    }
    // Parsed, but the module refuses it: set1 without its byte, a 32nd station.
    let cli = Cli::try_parse_from(["sim", "--start-code", "set1"]).unwrap();
    assert!(cli.args.micrex_config().is_err());
    let many: Vec<String> = (1..=32).map(|n| n.to_string()).collect();
    let cli = Cli::try_parse_from(["sim", "--mode", "3", "--stations", &many.join(",")]).unwrap();
    let err = cli.args.micrex_config().unwrap_err();
    assert!(err.to_string().contains("32 stations"), "{err}");
}
