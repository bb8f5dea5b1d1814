//! The cell file as a user meets it: good files load and round-trip; bad files are refused
//! with messages that name the key path, the value, what is allowed and the manual section,
//! every validation error at once.

use std::path::Path;

use cellgate::transport::{Parity, StopBits};
use cellgate_core::config::{CellConfig, ConfigError, ConfigErrors, Interface, TransportConfig};
use cellgate_core::fanuc::sat::Params;
use cellgate_core::fanuc::{CodeSystem, EndCode, Protocol};
use cellgate_core::fuji::frame::{self, BccCalc, BccCode, BccKind, BccRange};

fn example_path() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cell.toml")
}

fn errors(text: &str) -> ConfigErrors {
    match CellConfig::from_toml_str(text, "cell.toml") {
        Ok(cfg) => panic!("expected errors, got a valid cell: {cfg:?}"),
        Err(e) => e,
    }
}

fn messages(e: &ConfigErrors) -> Vec<String> {
    e.iter().map(ToString::to_string).collect()
}

/// A machine on a simulated line, with `extra` keys on the machine table.
fn one_machine(protocol: &str, extra: &str) -> String {
    format!(
        "cell = \"c\"\n\n[[machines]]\nname = \"mill-1\"\nprotocol = \"{protocol}\"\n{extra}\n\
         [machines.transport]\nkind = \"sim\"\nline = {{ baud = 19200 }}\n"
    )
}

#[test]
fn example_file_loads_with_every_key() {
    let cfg = CellConfig::load(&example_path()).unwrap();
    assert_eq!(cfg.cell, "line-3");
    assert_eq!(cfg.machines.len(), 4);
    assert_eq!(cfg.plcs.len(), 1);

    let mill1 = cfg.machine("mill-1").unwrap();
    assert_eq!(mill1.protocol, Protocol::A);
    assert_eq!(mill1.code, CodeSystem::Iso);
    assert_eq!(mill1.effective_end_code(), EndCode::Etx);
    assert_eq!(mill1.param_5000_bit3(), 1);
    assert_eq!(mill1.effective_interface(), Interface::Rs232c);
    assert_eq!(mill1.params(), Params::POWER_ON);
    let TransportConfig::Serial { path, line, .. } = &mill1.transport else {
        panic!("mill-1 is on a serial port: {:?}", mill1.transport);
    };
    assert_eq!(path, "/dev/ttyS0");
    assert_eq!(
        (line.baud, line.parity, line.stop_bits),
        (9600, Parity::Even, StopBits::One)
    );

    let mill2 = cfg.machine("mill-2").unwrap();
    assert_eq!(mill2.effective_packet_n(), 4);
    assert_eq!(mill2.effective_interface(), Interface::Rs422);
    assert!(matches!(
        &mill2.transport,
        TransportConfig::Tcp { address, window: Some(2048), .. } if address == "192.0.2.21:4001"
    ));

    let lathe = cfg.machine("lathe-1").unwrap();
    assert!(lathe.effective_notify_alarm_reset());
    assert_eq!(lathe.param_5000_bit3(), 1);

    let grinder = cfg.machine("grinder-1").unwrap();
    assert_eq!(grinder.board_sim().buffer_size, 8192);

    let plc = cfg.plc("plc-1").unwrap();
    assert_eq!((plc.mode, plc.stations.as_slice()), (2, &[1u8, 2][..]));
    assert_eq!(plc.frame.start_code, frame::StartCode::Colon);
    assert_eq!(plc.frame.end_code, frame::EndCode::Cr);
    assert_eq!(
        (
            plc.frame.bcc,
            plc.frame.bcc_range,
            plc.frame.bcc_calc,
            plc.frame.bcc_code
        ),
        (
            BccKind::Set1,
            BccRange::StartTextEnd,
            BccCalc::Add,
            BccCode::TransmissionCode
        )
    );
}

#[test]
fn good_files_round_trip() {
    let example = CellConfig::load(&example_path()).unwrap();
    for cfg in [CellConfig::embedded_default(), example] {
        let text = cfg.to_toml_string().unwrap();
        let again = CellConfig::from_toml_str(&text, "written")
            .unwrap_or_else(|e| panic!("written file does not read back:\n{e}\n---\n{text}"));
        assert_eq!(again, cfg);
    }
}

#[test]
fn embedded_default_is_the_demo_cell() {
    let cfg = CellConfig::embedded_default();
    assert!(cfg.validate().is_ok());
    assert_eq!(cfg.cell, "demo");
    assert_eq!(cfg.bus.listen, ["tcp/127.0.0.1:7447"]);
    assert!(!cfg.bus.multicast_scouting);
    let shape: Vec<(&str, Protocol, u32, u8)> = cfg
        .machines
        .iter()
        .map(|m| {
            assert!(matches!(m.transport, TransportConfig::Sim { .. }));
            (
                m.name.as_str(),
                m.protocol,
                m.transport.line().baud,
                m.effective_packet_n(),
            )
        })
        .collect();
    assert_eq!(
        shape,
        [
            ("mill-1", Protocol::A, 19_200, 0),
            ("mill-2", Protocol::ExpansionA, 86_400, 2),
            ("lathe-1", Protocol::B, 19_200, 0),
        ]
    );
    // One simulated PLC whose tags move by themselves (its [plcs.sim] ticks).
    assert_eq!(cfg.plcs.len(), 1);
    let plc = &cfg.plcs[0];
    assert_eq!(
        (plc.name.as_str(), plc.mode, plc.tags.len()),
        ("plc-1", 1, 4)
    );
    assert_eq!(plc.sim.ticks.len(), 2);
}

#[test]
fn out_of_range_parameter_names_its_path_and_bound() {
    let e = errors(&one_machine("a", "tw = 12"));
    assert_eq!(
        messages(&e),
        ["machines.mill-1.tw = 12: must be within 0..=5 (tp = 5) (§4.5)"]
    );
    assert_eq!(e.0[0].path().as_deref(), Some("machines.mill-1.tw"));

    // The bound follows the other parameter.
    let e = errors(&one_machine("a", "no = 100\nnb = 80"));
    assert_eq!(
        messages(&e),
        ["machines.mill-1.nb = 80: must be within 101..=4000 (1 + no) (§4.5)"]
    );
}

#[test]
fn unknown_key_is_named_with_its_line() {
    let e = errors(&one_machine("a", "polling = 5"));
    assert_eq!(e.len(), 1);
    let text = e.to_string();
    assert!(
        text.starts_with("cell.toml:6: unknown key `polling`"),
        "{text}"
    );
    assert!(text.contains("`tp`"), "the keys the table takes: {text}");
    assert!(matches!(e.0[0], ConfigError::Unknown { line: 6, .. }));

    // Inside the transport table too, at the key's own line.
    let text = errors(
        "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n[machines.transport]\n\
         kind = \"serial\"\npath = \"/dev/ttyS0\"\nbaud = 9600\n",
    )
    .to_string();
    assert!(text.contains("cell.toml:8: unknown key `baud`"), "{text}");
}

#[test]
fn duplicate_machine_name_names_both_positions() {
    let text = "cell = \"c\"\n\
                [[machines]]\nname = \"mill-1\"\nprotocol = \"a\"\ntransport = { kind = \"sim\" }\n\
                [[machines]]\nname = \"mill-2\"\nprotocol = \"a\"\ntransport = { kind = \"sim\" }\n\
                [[machines]]\nname = \"mill-1\"\nprotocol = \"b\"\ntransport = { kind = \"sim\" }\n";
    assert_eq!(
        messages(&errors(text)),
        [
            "machines.mill-1: [[machines]] #1 and [[machines]] #3 are both named \"mill-1\"; \
             names must be unique in a cell (each becomes a key chunk)"
        ]
    );
}

#[test]
fn missing_transport_is_named() {
    let text = "cell = \"c\"\n[[machines]]\nname = \"mill-1\"\nprotocol = \"a\"\n";
    assert_eq!(
        messages(&errors(text)),
        [
            "machines.mill-1.transport: missing; add a transport table with kind = \"serial\", \
             \"tcp\" or \"sim\""
        ]
    );
}

#[test]
fn transport_keys_follow_the_kind() {
    let text = "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n\
                [machines.transport]\nkind = \"serial\"\naddress = \"h:1\"\nwindow = 64\n";
    assert_eq!(
        messages(&errors(text)),
        [
            "machines.m.transport.address: used only with kind = \"tcp\", not \"serial\"; \
             remove the key",
            "machines.m.transport.window: used only with kind = \"tcp\", not \"serial\"; \
             remove the key",
            "machines.m.transport.path: missing; a serial transport names its device, e.g. \
             path = \"/dev/ttyS0\"",
        ]
    );
}

#[test]
fn several_errors_are_reported_at_once() {
    let text = r#"
cell = "line 3"

[[machines]]
name = "mill-1"
protocol = "a"
tw = 12
ti = 3
end_code = "etx"
interface = "rs232c"

[machines.transport]
kind = "serial"
path = "/dev/ttyS0"
line = { baud = 38400, parity = "odd", stop_bits = "1" }

[[machines]]
name = "mill-2"
protocol = "expansion-a"
packet_n = 3
interface = "rs232c"

[machines.transport]
kind = "sim"

[[machines]]
name = "lathe-1"
protocol = "b"
end_code = "cr"

[[machines]]
name = "mill-1"
protocol = "b"
transport = { kind = "tcp", address = "192.0.2.9:4001", line = { baud = 19200 }, window = 1024 }

[[plcs]]
name = "plc-1"
mode = 1
stations = [3]
bcc = "set1"
bcc_calc = "crc16"
transport = { kind = "serial", path = "/dev/ttyS1", line = { baud = 57600 } }
"#;
    let e = errors(text);
    let got = messages(&e);
    let expected = [
        "cell = \"line 3\": use only letters, digits, '_' and '-', at least one (the name \
         becomes a Zenoh key chunk)",
        "machines.mill-1: [[machines]] #1 and [[machines]] #4 are both named \"mill-1\"; names \
         must be unique in a cell (each becomes a key chunk)",
        "machines.mill-1.tw = 12: must be within 0..=5 (tp = 5) (§4.5)",
        "machines.mill-1.ti = 3: must be within 0..=10 in 2 ms steps (§4.5)",
        "machines.mill-1.transport.line.baud = 38400: RS-232-C carries 50..=19200 baud; set \
         interface = \"rs422\" for faster rates (§2.1)",
        "machines.mill-1.transport.line = \"38400 8O1\": the remote buffer frames characters as \
         8 data bits with even parity and 1 stop bit (\"8E1\") or with no parity and 2 stop \
         bits (\"8N2\") (§3.1, parameters 5072 / 5082)",
        "machines.mill-2.packet_n = 3: must be 1, 2 or 4 (packets of 256·n bytes); the board \
         takes any other value as 0, i.e. plain Protocol A (§5.2)",
        "machines.mill-2.interface = \"rs232c\": Expansion Protocol A runs on RS-422 only (§2.2)",
        "machines.lathe-1.end_code: Protocol B has no message end code (end_code = \"cr\"): only \
         Protocol A and Expansion Protocol A messages end with CR or ETX; remove the key \
         (§10.2, parameter 5000#3)",
        "machines.lathe-1.transport: missing; add a transport table with kind = \"serial\", \
         \"tcp\" or \"sim\"",
        "machines[4].transport.window = 1024: must be within 1..=511: the allowable overrun \
         after DC3 is less than 512 characters, and bytes handed to the device server cannot be \
         called back (§6.3)",
        "plcs.plc-1.transport.line.baud = 57600: must be one of 300, 600, 1200, 2400, 4800, \
         9600, 19200 (FFU120B §3-2, §4-3 item 4)",
        "plcs.plc-1.stations = [3]: mode 1 is a 1:1 link and addresses station 00 only: use \
         stations = [0] (FFU120B §5-3 RSNO)",
        "plcs.plc-1.bcc_range = \"text\": a CRC-16 BCC (item 22; initial error F2) must follow \
         the end code: use \"text+end\" or \"start+text+end\" (item 21) (FFU120B §4-3 items \
         21, 22, §4-7)",
        "plcs.plc-1.bcc_code = \"transmission-code\": a CRC-16 BCC (item 22) travels in binary: \
         set bcc_code = \"binary\" (item 23; initial error F3) (FFU120B §4-3 items 22, 23, §4-7)",
    ];
    for (i, (g, x)) in got.iter().zip(expected.iter()).enumerate() {
        assert_eq!(g, x, "error {i}");
    }
    assert_eq!(got.len(), expected.len(), "{got:#?}");
    // Display: one error per line.
    assert_eq!(e.to_string().lines().count(), expected.len());
}

#[test]
fn validate_checks_a_config_built_in_code() {
    let mut cfg = CellConfig::embedded_default();
    cfg.machines[0].tp = Some(0);
    cfg.machines[2].packet_n = Some(2);
    let e = cfg.validate().unwrap_err();
    assert_eq!(
        messages(&e),
        [
            "machines.mill-1.tp = 0: must be within 1..=99 (§4.5)",
            "machines.mill-1.tw = 5: must be within 0..=0 (tp = 0) (§4.5)",
            "machines.lathe-1.packet_n: Protocol B has no data packets: packet_n belongs to \
             Expansion Protocol A (§5.2)",
        ]
    );
}

#[test]
fn load_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("absent.toml");
    let e = CellConfig::load(&missing).unwrap_err();
    assert_eq!(e.len(), 1);
    let text = e.to_string();
    assert!(
        text.starts_with(&format!(
            "{}: cannot read the cell file: ",
            missing.display()
        )),
        "{text}"
    );

    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "cell = \"c\"\n[bus]\nmulticast = true\n").unwrap();
    let text = CellConfig::load(&bad).unwrap_err().to_string();
    assert!(
        text.starts_with(&format!(
            "{}:3: unknown key `multicast` (did you mean `multicast_scouting`?)",
            bad.display()
        )),
        "{text}"
    );
}

#[test]
fn summary_of_the_example() {
    let s = CellConfig::load(&example_path()).unwrap().summary();
    for expected in [
        "cell line-3",
        "bus: peer mode, keys under cellgate/line-3, listen tcp/127.0.0.1:7447, connect none, \
         multicast scouting off",
        "programs: in programs, at most 512 MiB each; punched programs stored; remote requests \
         (REQ O{n}) (PRG={n})",
        "  mill-1: Protocol A, ISO code (5000#2 = 1), RS-232-C",
        "    end code ETX (5000#3 = 1)",
        "    transport: serial /dev/ttyS0, 9600 8E1, reopened every 100..5000 ms while away",
        "  mill-2: Expansion Protocol A n = 4 (1024-byte packets), ASCII code (5000#2 = 0), RS-422",
        "  lathe-1: Protocol B, ASCII code (5000#2 = 1), RS-232-C",
        "    reset/alarm notification on (5000#3 = 1)",
        "    simulated board: buffer 8192 bytes, CNC takes 2000 bytes/s, 3 axes",
        "  plc-1: FFU120B mode 2, stations 01, 02",
        "    start code ':', end code CR, code transposition on, reply time-out 2000 ms",
        "    BCC add (set1, high byte first), over start+text+end, as transmission-code",
        "    transport: serial /dev/ttyS1, 9600 7E1, parity made and checked by the port, reopened every 100..5000 ms while away",
    ] {
        assert!(
            s.lines().any(|l| l == expected),
            "missing {expected:?} in\n{s}"
        );
    }
    // Protocol B has no SET: the §4.5 parameters are not shown for it.
    let lathe: Vec<&str> = s
        .lines()
        .skip_while(|l| !l.starts_with("  lathe-1:"))
        .skip(1)
        .take_while(|l| l.starts_with("    "))
        .collect();
    assert!(!lathe.is_empty(), "{s}");
    assert!(!lathe.iter().any(|l| l.contains("parameters")), "{lathe:?}");
}

#[test]
fn a_tags_mtconnect_type_and_units_are_checked() {
    let cell = |mt: &str| {
        format!(
            r#"
cell = "t"
[[plcs]]
name = "plc-1"
stations = [0]
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[[plcs.tags]]
name = "temp"
module = "D"
address = 0
type = "i16"
mtconnect = {mt}
[[plcs.tags]]
name = "flag"
module = "M"
address = 0
type = "bit"
bit = 0
mtconnect = {{ type = "PRESSURE" }}
"#
        )
    };
    let m = messages(&errors(&cell(r#"{ type = "TEMPRATURE" }"#)));
    assert!(
        m.iter().any(|e| e.contains("plcs.plc-1.tags.temp.mtconnect.type") && e.contains("TEMPERATURE")),
        "{m:#?}"
    );
    assert!(
        m.iter()
            .any(|e| e.contains("plcs.plc-1.tags.flag.mtconnect.type")
                && e.contains("a bit is no measurement")),
        "{m:#?}"
    );
    let m = messages(&errors(&cell(
        r#"{ type = "TEMPERATURE", units = "KELVIN" }"#,
    )));
    assert!(
        m.iter()
            .any(|e| e.contains("mtconnect.units") && e.contains("KELVIN")),
        "{m:#?}"
    );
    let m = messages(&errors(&cell(
        r#"{ type = "PART_COUNT", units = "COUNT" }"#,
    )));
    assert!(
        m.iter()
            .any(|e| e.contains("mtconnect.units") && e.contains("EVENT")),
        "{m:#?}"
    );
}

#[test]
fn folders_are_checked() {
    let m = messages(&errors(&format!(
        "{}\n[programs]\nwatch = \"sometimes\"\n",
        one_machine("a", "")
    )));
    assert!(m.iter().any(|e| e.contains("watch")), "{m:#?}");
    let text = r#"
cell = "t"
[programs]
dir = "programs"
extensions = [".nc"]
settle_ms = 10
[[machines]]
name = "mill-1"
protocol = "a"
transport = { kind = "sim", line = { baud = 19200 } }
drop_dir = "programs"
[[machines]]
name = "mill-2"
protocol = "a"
transport = { kind = "sim", line = { baud = 19200 } }
drop_dir = "drop"
receive_dir = "drop"
"#;
    let m = messages(&errors(text));
    for (key, says) in [
        ("programs.extensions[0]", "without the dot"),
        ("programs.settle_ms", "10"),
        ("machines.mill-1.drop_dir", "programs.dir"),
        ("machines.mill-2.receive_dir", "machines.mill-2.drop_dir"),
    ] {
        assert!(
            m.iter().any(|e| e.contains(key) && e.contains(says)),
            "{key}: {m:#?}"
        );
    }
}
