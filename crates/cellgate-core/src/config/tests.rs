//! Validation rules, one test per rule; `tests/cli/config.rs` covers the file as users meet it.
use super::fanuc::default_interface;
use super::*;
use crate::engine::LineSettings;
use crate::fanuc::sat::Params;
use crate::fanuc::{EndCode, Protocol};

const MINIMAL: &str = r#"
cell = "c1"
[[machines]]
name = "m1"
protocol = "a"
transport = { kind = "sim" }
"#;

fn errors_of(text: &str) -> Vec<String> {
    match CellConfig::from_toml_str(text, "test.toml") {
        Ok(_) => Vec::new(),
        Err(e) => e.iter().map(ToString::to_string).collect(),
    }
}

#[test]
fn request_patterns_are_checked() {
    let with = |requests: &str| format!("{MINIMAL}\n[programs]\nrequests = {requests}\n");
    assert!(errors_of(&with(r#"["(CALL {n})", "(PRG={n})"]"#)).is_empty());
    assert!(errors_of(&with("[]")).is_empty());
    let e = errors_of(&with(r#"["(REQ O{n})", "(REQ)", "({n}%)"]"#));
    assert_eq!(e.len(), 2, "{e:?}");
    assert!(
        e[0].contains("programs.requests[1]") && e[0].contains("{n}"),
        "{e:?}"
    );
    assert!(
        e[1].contains("programs.requests[2]") && e[1].contains("EOR"),
        "{e:?}"
    );
    let cfg = CellConfig::from_toml_str(MINIMAL, "t").unwrap();
    assert!(cfg.programs.store_punched);
    assert_eq!(cfg.programs.requests, ["(REQ O{n})", "(PRG={n})"]);
}

#[test]
fn minimal_file_takes_defaults() {
    let cfg = CellConfig::from_toml_str(MINIMAL, "t").unwrap();
    let m = &cfg.machines[0];
    assert_eq!(m.params(), Params::POWER_ON);
    assert_eq!(m.effective_end_code(), EndCode::Cr);
    assert_eq!(m.effective_packet_n(), 0);
    assert_eq!(m.effective_interface(), Interface::Rs232c);
    assert_eq!(m.transport.line(), &LineSettings::default());
    assert_eq!(m.board_sim(), BoardSimConfig::DEFAULT);
    assert_eq!(cfg.programs, ProgramsConfig::default());
    assert_eq!(cfg.bus, BusConfig::default());
}

#[test]
fn embedded_default_is_valid() {
    let cfg = CellConfig::embedded_default();
    assert_eq!(cfg.cell, "demo");
    let names: Vec<&str> = cfg.machines.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["mill-1", "mill-2", "lathe-1"]);
    assert!(cfg.bus.listen == ["tcp/127.0.0.1:7447"] && !cfg.bus.multicast_scouting);
    let mill2 = cfg.machine("mill-2").unwrap();
    assert_eq!(mill2.effective_packet_n(), 2);
    assert_eq!(mill2.effective_interface(), Interface::Rs422);
    assert!(cfg.validate().is_ok());
}

#[test]
fn interface_default_follows_baud_and_protocol() {
    assert_eq!(
        default_interface(Protocol::A, 19_200, None),
        Interface::Rs232c
    );
    assert_eq!(
        default_interface(Protocol::A, 38_400, None),
        Interface::Rs422
    );
    assert_eq!(
        default_interface(Protocol::ExpansionB, 9600, None),
        Interface::Rs422
    );
    assert_eq!(
        default_interface(Protocol::B, 9600, Some(Interface::Rs422)),
        Interface::Rs422
    );
}

#[test]
fn param_errors_carry_the_machine_path() {
    let errs = errors_of(&format!("{MINIMAL}tw = 12\n"));
    assert_eq!(
        errs,
        ["machines.m1.tw = 12: must be within 0..=5 (tp = 5) (§4.5)"]
    );
}

#[test]
fn packet_n_rules() {
    let file = |protocol: &str, n: &str| {
        format!(
            "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n{n}\n\
             transport = {{ kind = \"sim\", line = {{ baud = 86400 }} }}\n"
        )
    };
    assert!(errors_of(&file("expansion-a", "packet_n = 4")).is_empty());
    assert!(errors_of(&file("expansion-a", "")).is_empty());
    assert!(errors_of(&file("a", "packet_n = 0")).is_empty());
    let e = errors_of(&file("expansion-a", "packet_n = 3"));
    assert_eq!(e.len(), 1);
    assert!(e[0].starts_with("machines.m.packet_n = 3: must be 1, 2 or 4"));
    assert!(e[0].ends_with("(§5.2)"));
    let e = errors_of(&file("expansion-a", "packet_n = 0"));
    assert!(e[0].contains("n = 0 is plain Protocol A"), "{e:?}");
    let e = errors_of(&file("a", "packet_n = 2"));
    assert!(e[0].starts_with("machines.m.packet_n = 2: Protocol A sends NC data"));
    let e = errors_of(&file("expansion-b", "packet_n = 1"));
    assert!(e[0].starts_with("machines.m.packet_n: Expansion Protocol B has no data packets"));
}

#[test]
fn di_poll_rules() {
    let file = |protocol: &str, key: &str| {
        format!(
            "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n{key}\n\
             transport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\n"
        )
    };
    assert!(errors_of(&file("a", "di_poll_ms = 500")).is_empty());
    let e = errors_of(&file("a", "di_poll_ms = 10"));
    assert_eq!(e.len(), 1);
    assert!(e[0].starts_with("machines.m.di_poll_ms = 10: must be within 100..=3600000"));
    let e = errors_of(&file("b", "di_poll_ms = 500"));
    assert_eq!(e.len(), 1);
    assert!(
        e[0].starts_with("machines.m.di_poll_ms: Protocol B has no RDI/SDI"),
        "{e:?}"
    );
    let c = CellConfig::from_toml_str(&file("a", "di_poll_ms = 500"), "t").unwrap();
    assert_eq!(c.machines[0].di_poll_ms, Some(500));
    let back = CellConfig::from_toml_str(&c.to_toml_string().unwrap(), "t").unwrap();
    assert_eq!(back, c);
}

#[test]
fn family_specific_keys() {
    let b = |extra: &str| {
        format!(
            "cell = \"c\"\n[[machines]]\nname = \"l\"\nprotocol = \"b\"\n{extra}\n\
             transport = {{ kind = \"sim\" }}\n"
        )
    };
    assert!(errors_of(&b("notify_alarm_reset = true")).is_empty());
    let e = errors_of(&b("end_code = \"etx\""));
    assert_eq!(e.len(), 1);
    assert!(e[0].starts_with("machines.l.end_code: Protocol B has no message end code"));
    let e = errors_of(&format!("{MINIMAL}notify_alarm_reset = true\n"));
    assert!(e[0].starts_with("machines.m1.notify_alarm_reset: Protocol A does not post"));
}

#[test]
fn baud_rates_and_interfaces() {
    let f = |protocol: &str, baud: u32, interface: &str| {
        format!(
            "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n{interface}\n\
             transport = {{ kind = \"sim\", line = {{ baud = {baud} }} }}\n"
        )
    };
    assert!(errors_of(&f("a", 19200, "")).is_empty());
    assert!(errors_of(&f("a", 86400, "")).is_empty());
    assert!(errors_of(&f("expansion-b", 76800, "")).is_empty());
    let e = errors_of(&f("a", 115_200, ""));
    assert!(e[0].starts_with("machines.m.transport.line.baud = 115200: must be one of"));
    assert!(e[0].ends_with("76800, 86400 (§10.2)"));
    let e = errors_of(&f("a", 38_400, "interface = \"rs232c\""));
    assert_eq!(
        e,
        [
            "machines.m.transport.line.baud = 38400: RS-232-C carries 50..=19200 baud; \
             set interface = \"rs422\" for faster rates (§2.1)"
        ]
    );
    let e = errors_of(&f("b", 38_400, ""));
    assert!(
        e[0].contains("Protocol B runs at 19200 baud at most"),
        "{e:?}"
    );
    let e = errors_of(&f("expansion-a", 19_200, "interface = \"rs232c\""));
    assert_eq!(
        e,
        [
            "machines.m.interface = \"rs232c\": Expansion Protocol A runs on RS-422 only \
             (§2.2)"
        ]
    );
}

#[test]
fn fanuc_framing() {
    let f = |line: &str| {
        format!(
            "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n\
             transport = {{ kind = \"sim\", line = {{ {line} }} }}\n"
        )
    };
    assert!(errors_of(&f("parity = \"even\", stop_bits = \"1\"")).is_empty());
    assert!(errors_of(&f("parity = \"none\", stop_bits = \"2\"")).is_empty());
    let e = errors_of(&f("parity = \"none\", stop_bits = \"1\""));
    assert_eq!(e.len(), 1);
    assert!(e[0].starts_with("machines.m.transport.line = \"9600 8N1\": the remote buffer"));
    assert!(errors_of(&f("data_bits = \"7\"")).len() == 1);
    assert!(errors_of(&f("parity = \"odd\", stop_bits = \"1\"")).len() == 1);
}

#[test]
fn tcp_transport_checks() {
    let f = |protocol: &str, t: &str| {
        format!(
            "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n\
             transport = {{ kind = \"tcp\", {t} }}\n"
        )
    };
    assert!(errors_of(&f("a", "address = \"127.0.0.1:4001\"")).is_empty());
    assert!(errors_of(&f("a", "address = \"moxa-3.local:4001\"")).is_empty());
    assert!(errors_of(&f("a", "address = \"[::1]:4001\"")).is_empty());
    let e = errors_of(&f("a", "address = \"moxa-3\""));
    assert!(e[0].starts_with("machines.m.transport.address = \"moxa-3\": must be host:port"));
    let e = errors_of(&f("b", "address = \"h:1\", window = 1024"));
    assert_eq!(e.len(), 1);
    assert!(e[0].starts_with("machines.m.transport.window = 1024: must be within 1..=511"));
    assert!(errors_of(&f("expansion-b", "address = \"h:1\", window = 1024")).is_empty());
    // The window in force: the file's, else the protocol's.
    let window = |protocol: &str, t: &str| {
        CellConfig::from_toml_str(&f(protocol, t), "t")
            .unwrap()
            .machines[0]
            .tcp_window()
    };
    assert_eq!(window("a", "address = \"h:1\""), 2048);
    assert_eq!(window("expansion-a", "address = \"h:1\""), 2048);
    assert_eq!(window("b", "address = \"h:1\""), 256);
    assert_eq!(window("expansion-b", "address = \"h:1\""), 256);
    assert_eq!(window("a", "address = \"h:1\", window = 300"), 300);
    assert_eq!(window("b", "address = \"h:1\", window = 300"), 300);
    // A PLC's (or any link's) own window wins over the default it is opened with.
    let t = |w: &str| -> TransportConfig {
        toml::from_str(&format!("kind = \"tcp\"\naddress = \"h:1\"\n{w}")).unwrap()
    };
    assert_eq!(t("window = 100").window_or(256), 100);
    assert_eq!(t("").window_or(256), 256);
    let e = errors_of(&f(
        "a",
        "address = \"h:1\", reconnect_min_ms = 500, reconnect_max_ms = 100",
    ));
    assert_eq!(
        e,
        [
            "machines.m.transport.reconnect_max_ms = 100: must be within 500..=3600000 \
             (reconnect_min_ms or more)"
        ]
    );
}

#[test]
fn transport_tables() {
    let e = errors_of(&MINIMAL.replace("{ kind = \"sim\" }", "{}"));
    assert_eq!(
        e,
        ["machines.m1.transport.kind: missing; one of \"serial\", \"tcp\" or \"sim\""]
    );
    let e = errors_of(&MINIMAL.replace("{ kind = \"sim\" }", "{ kind = \"tcp\" }"));
    assert!(e[0].starts_with("machines.m1.transport.address: missing; a tcp transport"));

    // Read on its own, a transport reports its problems through serde.
    let t: TransportConfig =
        toml::from_str("kind = \"tcp\"\naddress = \"h:1\"\nline = { baud = 19200 }").unwrap();
    assert_eq!(
        t,
        TransportConfig::Tcp {
            address: "h:1".to_string(),
            line: LineSettings::with_baud(19_200),
            parity_by: None,
            window: None,
            reconnect_min_ms: 100,
            reconnect_max_ms: 5000,
        }
    );
    let err = toml::from_str::<TransportConfig>("kind = \"sim\"\npath = \"/dev/x\"")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("`path`: used only with kind = \"serial\", not \"sim\""),
        "{err}"
    );
}

#[test]
fn sim_table_only_with_sim_transport() {
    let text = "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n\
                transport = { kind = \"serial\", path = \"/dev/ttyS0\" }\n\
                [machines.sim]\nbuffer_size = 8192\n";
    let e = errors_of(text);
    assert_eq!(e.len(), 1);
    assert!(e[0].starts_with("machines.m.sim: board simulation settings"));
    let e = errors_of(&format!(
        "{MINIMAL}[machines.sim]\nbuffer_size = 100\naxes = 0\n"
    ));
    assert_eq!(e.len(), 2, "{e:?}");
    assert!(e[0].starts_with("machines.m1.sim.buffer_size = 100: must be within 4096..="));
    assert!(e[1].starts_with("machines.m1.sim.axes = 0: must be within 1..=24"));
}

#[test]
fn names_must_be_key_chunks_and_unique_across_links() {
    let text = r#"
cell = "my cell"
[[machines]]
name = "m/1"
protocol = "a"
transport = { kind = "sim" }
[[machines]]
name = "x"
protocol = "a"
transport = { kind = "sim" }
[[plcs]]
name = "x"
transport = { kind = "sim" }
"#;
    let e = errors_of(text);
    assert_eq!(e.len(), 3, "{e:?}");
    assert!(e[0].starts_with("cell = \"my cell\": use only letters"));
    assert!(e[1].starts_with("machines[1].name = \"m/1\": use only letters"));
    assert_eq!(
        e[2],
        "plcs.x: [[machines]] #2 and [[plcs]] #1 are both named \"x\"; names must be \
         unique in a cell (each becomes a key chunk)"
    );
}

#[test]
fn plc_defaults_and_initial_errors() {
    let f = |extra: &str| {
        format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\n{extra}\n\
             transport = {{ kind = \"sim\" }}\n"
        )
    };
    let cfg = CellConfig::from_toml_str(&f(""), "t").unwrap();
    let p = &cfg.plcs[0];
    assert_eq!((p.mode, p.stations.as_slice()), (1, &[0u8][..]));
    assert_eq!(p.frame.start_bytes(), b":");
    assert_eq!(p.frame.end_bytes(), b"\r");
    assert!(p.frame.transposition);

    // F1: binary BCC before the end code.
    let e = errors_of(&f("bcc = \"set1\"\nbcc_code = \"binary\""));
    assert_eq!(e.len(), 1);
    assert!(
        e[0].starts_with("plcs.p.bcc_range = \"text\": a binary BCC (item 23; initial error F1)"),
        "{e:?}"
    );
    // F2 + F3.
    let e = errors_of(&f("bcc = \"set1\"\nbcc_calc = \"crc16\""));
    assert_eq!(e.len(), 2, "{e:?}");
    assert!(
        e[0].contains("a CRC-16 BCC (item 22; initial error F2)"),
        "{e:?}"
    );
    assert!(e[1].starts_with("plcs.p.bcc_code = \"transmission-code\": a CRC-16 BCC"));
    assert!(e[1].contains("initial error F3"), "{e:?}");
    // F5: a Set 1 end code without its byte.
    let e = errors_of(&f("end_code = \"set1\""));
    assert_eq!(e.len(), 1, "{e:?}");
    assert!(
        e[0].starts_with("plcs.p.end_codes = []: end_code = \"set1\" sets no end code")
            && e[0].contains("initial error F5"),
        "{e:?}"
    );
    // F6: EBCDIC (item 13) with 7 data bits (item 5), on the key that selects it.
    let g = |line: &str| {
        format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\ncode = \"ebcdic\"\n\
             transport = {{ kind = \"sim\", line = {{ baud = 9600, {line} }} }}\n"
        )
    };
    let e = errors_of(&g("data_bits = 7, parity = \"even\", stop_bits = 1"));
    assert_eq!(e.len(), 1, "{e:?}");
    assert!(
        e[0].starts_with("plcs.p.code = \"ebcdic\": EBCDIC (item 13) is an 8-bit code")
            && e[0].contains("initial error F6"),
        "{e:?}"
    );
    // Every character format the initial file allows (items 5–7) is taken.
    for line in [
        "data_bits = 8, parity = \"none\", stop_bits = 1",
        "data_bits = 8, parity = \"odd\", stop_bits = 1.5",
        "data_bits = 8, parity = \"even\", stop_bits = 2",
    ] {
        let cfg =
            CellConfig::from_toml_str(&g(line), "t").unwrap_or_else(|e| panic!("{line}: {e}"));
        assert_eq!(
            cfg.plcs[0].frame.code,
            crate::fuji::frame::TransmissionCode::Ebcdic
        );
    }
    for line in [
        "data_bits = 7, parity = \"none\", stop_bits = 2",
        "data_bits = 7, parity = \"odd\", stop_bits = 1",
        "data_bits = 7, parity = \"even\", stop_bits = 1.5",
    ] {
        let ascii = format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\n\
             transport = {{ kind = \"sim\", line = {{ baud = 9600, {line} }} }}\n"
        );
        assert_eq!(errors_of(&ascii), Vec::<String>::new(), "{line}");
    }
    assert!(
        errors_of(&f(
            "bcc = \"set2\"\nbcc_calc = \"crc16\"\nbcc_code = \"binary\"\nbcc_range = \"start+text+end\""
        ))
        .is_empty()
    );
}

#[test]
fn plc_stations_modes_and_codes() {
    let f = |extra: &str| {
        format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\n{extra}\n\
             transport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\n"
        )
    };
    assert!(errors_of(&f("mode = 2\nstations = [1, 2, 31]")).is_empty());
    let e = errors_of(&f("stations = [1]"));
    assert!(e[0].starts_with("plcs.p.stations = [1]: mode 1 is a 1:1 link"));
    let e = errors_of(&f("mode = 3\nstations = [5, 120, 5]"));
    assert_eq!(e.len(), 2, "{e:?}");
    assert!(e[0].contains("station 120 is not a station number"));
    assert!(e[1].contains("each station number may appear once"));
    let e = errors_of(&f("mode = 6"));
    assert!(e[0].starts_with("plcs.p.mode = 6: must be 1 (1:1), 2 or 3"));
    let e = errors_of(&f("end_code = \"set2\"\nend_codes = [0x0D]"));
    assert_eq!(
        e,
        [
            "plcs.p.end_codes = [13]: end_code = \"set2\" needs exactly 2 bytes, e.g. \
             end_codes = [0x2A, 0x2A] (FFU120B §4-3 items 18, 19)"
        ]
    );
    let e = errors_of(&f("start_codes = [0x02]"));
    assert!(e[0].starts_with("plcs.p.start_codes: used only with start_code = \"set1\""));
    assert!(errors_of(&f("start_code = \"set1\"\nstart_codes = [0x2A]")).is_empty());
}

/// Modes 4 and 5 (non-procedure, FFU120B notes 9): messages both ways, no station, no tags;
/// `fixed_length` (item 15) and `receive_message` (item 3) only there.
#[test]
fn plc_non_procedure_modes() {
    let f = |extra: &str| {
        format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\n{extra}\n\
             transport = {{ kind = \"sim\", line = {{ baud = 9600 }} }}\n"
        )
    };
    let cfg = CellConfig::from_toml_str(&f("mode = 4\nfixed_length = 16"), "t").unwrap();
    let p = &cfg.plcs[0];
    assert!(p.is_non_procedure());
    assert_eq!((p.fixed_length, p.receive_message), (Some(16), 1));
    assert_eq!(p.master_settings().fixed_length, Some(16));
    let cfg = CellConfig::from_toml_str(&f("mode = 5\nreceive_message = 7"), "t").unwrap();
    assert_eq!(
        (cfg.plcs[0].fixed_length, cfg.plcs[0].receive_message),
        (None, 7)
    );
    let e = errors_of(&format!(
        "{}[[plcs.tags]]\nname = \"t\"\nmodule = \"D\"\naddress = 0\ntype = \"u16\"\n",
        f("mode = 5\nstations = [3]\nfixed_length = 300")
    ));
    assert_eq!(e.len(), 3, "{e:?}");
    assert!(
        e[0].starts_with("plcs.p.stations = [3]: modes 4 and 5 address no station"),
        "{e:?}"
    );
    assert!(
        e[1].starts_with("plcs.p.tags: tags are read with the command set"),
        "{e:?}"
    );
    assert!(
        e[2].starts_with("plcs.p.fixed_length = 300: must be 0"),
        "{e:?}"
    );
    let e = errors_of(&f("fixed_length = 8\nreceive_message = 2"));
    assert_eq!(e.len(), 2, "{e:?}");
    assert!(
        e[0].starts_with("plcs.p.fixed_length: a non-procedure setting"),
        "{e:?}"
    );
    assert!(
        e[1].starts_with("plcs.p.receive_message: a non-procedure setting"),
        "{e:?}"
    );
}

/// The start-up overview says what each mode carries (FFU120B §1-3, §5-2): memory and
/// transfers in mode 1, memory in modes 2–3, and messages, never memory, in modes 4–5.
#[test]
fn plc_overview_says_what_each_mode_carries() {
    let f = |extra: &str| {
        format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\n{extra}\n\
             transport = {{ kind = \"sim\", line = {{ baud = 9600 }} }}\n"
        )
    };
    let overview = |extra: &str| {
        CellConfig::from_toml_str(&f(extra), "t")
            .unwrap()
            .overview(4)
    };
    let four = overview("mode = 4\nfixed_length = 12\nreceive_message = 9");
    assert!(
        four.contains(
            "mode 4, simulated, 9600 baud: messages of 12 bytes both ways, to receive message 9"
        ),
        "{four}"
    );
    assert!(
        !four.contains("memory") && !four.contains("transfers"),
        "{four}"
    );
    let five = overview("mode = 5");
    assert!(
        five.contains(": messages both ways (variable length), to receive message 1"),
        "{five}"
    );
    assert!(overview("mode = 1").contains(": memory, transfers"));
    let three = overview("mode = 3\nstations = [1, 2]");
    assert!(
        three.contains(": memory") && !three.contains("transfers"),
        "{three}"
    );
}

/// `parity_by` (FFU120B §4-3 items 5–6): on a serial port or a device server only, "gateway"
/// only on a line of 7 data bits with parity, whose port then runs 8 data bits and no parity;
/// a 7-bit line over a device server without the key is warned of, with it not.
#[test]
fn parity_by_where_a_7_bit_lines_parity_bit_is_made() {
    let f = |transport: &str| {
        format!("cell = \"c\"\n[[plcs]]\nname = \"p\"\nmode = 4\ntransport = {transport}\n")
    };
    let seven = "line = { data_bits = 7, parity = \"odd\", stop_bits = 2 }";
    let cfg = CellConfig::from_toml_str(
        &f(&format!(
            "{{ kind = \"serial\", path = \"/dev/ttyS0\", parity_by = \"gateway\", {seven} }}"
        )),
        "t",
    )
    .unwrap();
    let t = &cfg.plcs[0].transport;
    assert_eq!(t.parity_by(), crate::engine::parity::ParityBy::Gateway);
    assert_eq!(t.port_line().to_string(), "9600 8N2");
    assert!(cfg.warnings().is_empty(), "{:?}", cfg.warnings());
    let back = CellConfig::from_toml_str(&cfg.to_toml_string().unwrap(), "t").unwrap();
    assert_eq!(back.plcs[0].transport, *t);

    let cfg = CellConfig::from_toml_str(
        &f(&format!("{{ kind = \"tcp\", address = \"h:1\", {seven} }}")),
        "t",
    )
    .unwrap();
    assert_eq!(
        cfg.plcs[0].transport.port_line(),
        *cfg.plcs[0].transport.line()
    );
    let w = cfg.warnings();
    assert_eq!(w.len(), 1, "{w:?}");
    assert!(
        w[0].starts_with("plcs.p.transport: 7 data bits with odd parity"),
        "{w:?}"
    );
    let cfg = CellConfig::from_toml_str(
        &f(&format!(
            "{{ kind = \"tcp\", address = \"h:1\", parity_by = \"port\", {seven} }}"
        )),
        "t",
    )
    .unwrap();
    assert!(cfg.warnings().is_empty());

    let e = errors_of(&f("{ kind = \"sim\", parity_by = \"gateway\" }"));
    assert!(
        e[0].starts_with("plcs.p.transport.parity_by: used only with kind = \"serial\" or \"tcp\""),
        "{e:?}"
    );
    let e = errors_of(&f(
        "{ kind = \"tcp\", address = \"h:1\", parity_by = \"gateway\", line = { data_bits = 7 } }",
    ));
    assert!(
        e[0].starts_with(
            "plcs.p.transport.parity_by = \"gateway\": the gateway carries a parity bit"
        ),
        "{e:?}"
    );
}

#[test]
fn plc_baud_rates() {
    let text = "cell = \"c\"\n[[plcs]]\nname = \"p\"\n\
                transport = { kind = \"tcp\", address = \"h:1\", line = { baud = 38400 } }\n";
    assert_eq!(
        errors_of(text),
        [
            "plcs.p.transport.line.baud = 38400: must be one of 300, 600, 1200, 2400, 4800, \
             9600, 19200 (FFU120B §3-2, §4-3 item 4)"
        ]
    );
}

#[test]
fn bus_and_telemetry_checks() {
    let text = "cell = \"c\"\n[bus]\nprefix = \"a//b\"\nlisten = [\"127.0.0.1:7447\"]\n\
                [telemetry]\notlp_endpoint = \"127.0.0.1:4317\"\nprometheus = \"localhost:9464\"\n";
    let e = errors_of(text);
    assert_eq!(e.len(), 4, "{e:?}");
    assert!(e[0].starts_with("bus.prefix = \"a//b\""));
    assert!(e[1].starts_with("bus.listen[1] = \"127.0.0.1:7447\""));
    assert!(e[2].starts_with("telemetry.otlp_endpoint"));
    assert!(
        e[3].starts_with("telemetry.prometheus = \"localhost:9464\""),
        "{}",
        e[3]
    );
    assert!(e[3].contains("IP address and port"), "{}", e[3]);
    let ok = "cell = \"c\"\n[telemetry]\nprometheus = \"127.0.0.1:9464\"\n";
    let config = CellConfig::from_toml_str(ok, "ok").unwrap();
    assert_eq!(
        config.telemetry.prometheus.as_deref(),
        Some("127.0.0.1:9464")
    );
}

#[test]
fn missing_keys_are_validation_errors() {
    let text = "[[machines]]\ntw = 9\n[[plcs]]\nname = \"p\"\n";
    let e = errors_of(text);
    assert_eq!(e.len(), 6, "{e:?}");
    assert!(e[0].starts_with("cell: missing;"));
    assert_eq!(
        e[1],
        "machines[1].name: missing; every [[machines]] #1 table needs a name"
    );
    assert!(e[2].starts_with("machines[1].protocol: missing;"));
    assert_eq!(
        e[3],
        "machines[1].tw = 9: must be within 0..=5 (tp = 5) (§4.5)"
    );
    assert!(e[4].starts_with("machines[1].transport: missing;"));
    assert!(e[5].starts_with("plcs.p.transport: missing;"));
}

#[test]
fn summary_shows_values_in_force() {
    let s = CellConfig::embedded_default().summary();
    assert!(s.starts_with("cell demo\n"), "{s}");
    assert!(
        s.contains("mill-2: Expansion Protocol A n = 2 (512-byte packets)"),
        "{s}"
    );
    assert!(
        s.contains("lathe-1: Protocol B, ISO code (5000#2 = 0), RS-232-C"),
        "{s}"
    );
    assert!(s.contains("Nb=2000 No=50"), "{s}");
}

#[test]
fn every_time_out_of_the_manual_gives_engine_settings_that_run() {
    // To may be 1..=999 s (§4.5); the host's WAT grace and dummy-packet interval follow it.
    for to in [1, 2, 10, 20, 999] {
        for protocol in ["a", "expansion-a"] {
            let text = MINIMAL.replace(
                "protocol = \"a\"",
                &format!("protocol = \"{protocol}\"\nto = {to}"),
            );
            let cell = CellConfig::from_toml_str(&text, "t").unwrap();
            let settings = cell.machines[0].protocol_a_config().unwrap();
            assert_eq!(settings.validate(), vec![], "to = {to}, {protocol}");
            crate::fanuc::protocol_a::ProtocolAHost::new(settings, std::time::Instant::now())
                .unwrap();
        }
    }
}

#[test]
fn g05_format_keys_are_kebab_case_and_default_to_the_parameters_at_zero() {
    use crate::fanuc::g05::{AuxFunction, AuxOrder, DataFormat, G05Format, UnitTime};
    #[derive(serde::Deserialize)]
    struct W {
        g05: G05Config,
    }
    let w: W = toml::from_str(
        "g05 = { axes = 3, data_format = \"general\", aux = \"m\", unit_time_ms = 2, aux_order = \"low-first\" }",
    )
    .unwrap();
    assert_eq!(
        w.g05.format(),
        G05Format {
            axes: 3,
            data_format: DataFormat::General,
            aux: AuxFunction::M,
            unit_time_ms: UnitTime::Ms2,
            aux_order: AuxOrder::LowFirst,
        }
    );
    let w: W = toml::from_str("g05 = { axes = 2 }").unwrap();
    assert_eq!(w.g05.format(), G05Format::new(2));
    let e = toml::from_str::<W>("g05 = { axes = 2, unit_time_ms = 3 }")
        .err()
        .unwrap();
    assert!(e.to_string().contains("7618"), "{e}");
    assert!(toml::from_str::<W>("g05 = { axes = 2, rds = 1 }").is_err());
    assert!(toml::from_str::<W>("g05 = { axes = 2, aux = \"b\" }").is_err());
    let mut g = w.g05;
    g.format.aux = AuxFunction::Second;
    g.format.axes = 4;
    let back = toml::to_string(&g).unwrap();
    assert!(back.contains("unit_time_ms = 8"), "{back}");
    assert!(back.contains("aux = \"second\""), "{back}");
}

#[test]
fn g05_rules() {
    let cell = |protocol: &str, baud: u32, g05: &str| {
        format!(
            "cell = \"c1\"\n[[machines]]\nname = \"m1\"\nprotocol = \"{protocol}\"\n\
             transport = {{ kind = \"sim\", line = {{ baud = {baud} }} }}\n[machines.g05]\n{g05}\n"
        )
    };
    // 3 axes, T = 8 ms: 7-byte blocks, 7 × 11 × 1000 / 8 = 9625 baud (§9.2).
    let ok = CellConfig::from_toml_str(&cell("a", 19_200, "axes = 3"), "t").unwrap();
    let g = ok.machines[0].g05.as_ref().unwrap();
    assert_eq!(g.required_baud(ok.machines[0].transport.line()), 9625);
    // 125 blocks in a second, raised to the 8 KiB of blocks a DAT needs.
    assert_eq!((g.window_blocks(), g.prime_blocks()), (1171, 62));
    assert_eq!(g.before, "G05\n");
    assert!(ok.summary().contains("G05: 3 axes, special format"));

    let e = errors_of(&cell("a", 9600, "axes = 3"));
    assert!(
        e.len() == 1 && e[0].contains("line.baud = 9600") && e[0].contains("9625 baud"),
        "{e:?}"
    );
    let e = errors_of(&cell("a", 19_200, "axes = 3\ndata_format = \"general\""));
    assert!(e.len() == 1 && e[0].contains("special format"), "{e:?}");
    assert!(errors_of(&cell("b", 19_200, "axes = 3\ndata_format = \"general\"")).is_empty());
    // The simulated CNC has 3 axes unless its `sim` table says otherwise.
    let e = errors_of(&cell("b", 19_200, "axes = 4"));
    assert!(e.len() == 1 && e[0].contains("controlled axes"), "{e:?}");
    let e = errors_of(&cell("b", 19_200, "axes = 3\nbefore = \"G01 X1\\n\""));
    assert!(e.len() == 1 && e[0].contains("g05.before"), "{e:?}");
    let e = errors_of(&cell("b", 19_200, "axes = 3\nafter = \"M30\\n%\""));
    assert!(e.len() == 1 && e[0].contains("g05.after"), "{e:?}");
    let e = errors_of(&cell("b", 19_200, "axes = 3\nunit_time_ms = 3"));
    assert!(e.len() == 1 && e[0].contains("unit_time_ms"), "{e:?}");
}

/// The priming level on a board that uses data in whole pieces covers the next piece's
/// exchange (§9.2, §4.4.2 3, §5.2), and `check-config` warns of a line and unit time that
/// cannot keep a stream going, from a waiting CNC or at all.
#[test]
fn g05_priming_and_warnings_follow_the_board() {
    let cell = |protocol: &str, baud: u32, extra: &str, g05: &str| {
        format!(
            "cell = \"c1\"\n[[machines]]\nname = \"m1\"\nprotocol = \"{protocol}\"\n{extra}\n\
             transport = {{ kind = \"sim\", line = {{ baud = {baud} }} }}\n\
             sim = {{ axes = 8 }}\n[machines.g05]\n{g05}\n"
        )
    };
    let load = |text: String| CellConfig::from_toml_str(&text, "t").unwrap();
    // 6 axes every 4 ms at 38 400 baud, Tx = Ti = 0: a DAT of Nb − No = 1950 bytes and its
    // GTD, 1962 characters, take 562 ms: 500 ms of blocks (125) are raised to 142.
    let c = load(cell(
        "a",
        38_400,
        "tx = 0\nti = 0",
        "axes = 6\nunit_time_ms = 4",
    ));
    let (m, g) = (&c.machines[0], c.machines[0].g05.as_ref().unwrap());
    let r = m.g05_refill().unwrap();
    assert_eq!((r.piece, r.data, r.time.as_millis()), ("DAT", 1950, 562));
    assert_eq!((g.prime_blocks(), g.prime_blocks_on(Some(r))), (125, 142));
    assert!(
        c.summary().contains("priming 125 raised to 142"),
        "{}",
        c.summary()
    );
    assert!(c.warnings().is_empty(), "{:?}", c.warnings());
    // The board's Tx (100 ms) and Ti (10 ms between its characters) at their power-on values
    // make every exchange 150 ms longer: a DAT's 150 blocks (600 ms) no longer last it.
    let c = load(cell("a", 38_400, "", "axes = 6\nunit_time_ms = 4"));
    let w = c.warnings();
    assert!(
        w.len() == 1
            && w[0].starts_with("machines.m1.g05: G05 cannot keep up on this line")
            && w[0].contains("150 blocks"),
        "{w:?}"
    );
    // Keeping up, but a long `before` leaves the first DAT 111 blocks (444 ms).
    let long = format!(
        "axes = 6\nunit_time_ms = 4\nbefore = \"{}G05\\n\"",
        "(X)".repeat(166) + "(Y)("
    );
    let c = load(cell(
        "a",
        38_400,
        "tx = 0\nti = 0",
        &long.replace("(Y)(", "(Y)\\n"),
    ));
    let w = c.warnings();
    assert!(
        w.len() == 1 && w[0].contains("started while the CNC waits runs dry"),
        "{w:?}"
    );
    // Expansion A: packets back to back; Protocol B reads bytes as they come.
    let c = load(cell(
        "expansion-a",
        86_400,
        "packet_n = 2",
        "axes = 3\nunit_time_ms = 2",
    ));
    let r = c.machines[0].g05_refill().unwrap();
    assert_eq!((r.piece, r.data), ("data packet", 512));
    assert!(c.warnings().is_empty(), "{:?}", c.warnings());
    let c = load(cell("b", 19_200, "", "axes = 3"));
    assert_eq!(c.machines[0].g05_refill(), None);
}

/// PEM-looking files (validation checks the blocks, zenoh the cryptography) and a cell file
/// with `security` appended, listening on TLS.
fn secured(dir: &std::path::Path, security: &str) -> String {
    let cert = "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n";
    std::fs::write(dir.join("ca.pem"), cert).unwrap();
    std::fs::write(dir.join("gw.pem"), cert).unwrap();
    std::fs::write(
        dir.join("gw-key.pem"),
        "-----BEGIN PRIVATE KEY-----\nMIIE\n-----END PRIVATE KEY-----\n",
    )
    .unwrap();
    std::fs::write(dir.join("users.txt"), "mes:s3cret\n\nops : also-secret\n").unwrap();
    format!(
        "{MINIMAL}\n[bus]\nlisten = [\"tls/127.0.0.1:7447\"]\n{}",
        security.replace("DIR", &dir.display().to_string())
    )
}

const TLS: &str = r#"
[security.tls]
ca = "DIR/ca.pem"
certificate = "DIR/gw.pem"
private_key = "DIR/gw-key.pem"
"#;

#[test]
fn a_secured_cell_loads_round_trips_and_is_summarised_without_secrets() {
    let dir = tempfile::tempdir().unwrap();
    let text = secured(
        dir.path(),
        &format!(
            "[security]\nusers_file = \"DIR/users.txt\"\n{TLS}\
             [[security.roles]]\nname = \"mes\"\ncert_common_names = [\"mes-1\"]\n\
             usernames = [\"mes\"]\n\
             permissions = [\"job.submit\", \"program.write\", \"job.submit\"]\n\
             [[security.roles]]\nname = \"dashboard\"\ncert_common_names = [\"dash\"]\n\
             permissions = [\"status.read\"]\n"
        ),
    );
    let cfg = CellConfig::from_toml_str(&text, "t").unwrap_or_else(|e| panic!("{e}\n{text}"));
    let s = &cfg.security;
    let tls = s.tls.as_ref().unwrap();
    assert!(tls.require_client_certificates && tls.verify_name_on_connect);
    assert_eq!(s.roles.len(), 2);
    assert_eq!(
        s.roles[0].permissions,
        [Permission::JobSubmit, Permission::ProgramWrite]
    );
    let back = CellConfig::from_toml_str(&cfg.to_toml_string().unwrap(), "t").unwrap();
    assert_eq!(back, cfg);
    let summary = cfg.summary();
    assert!(
        summary.contains("client certificates required"),
        "{summary}"
    );
    assert!(
        summary.contains("mes: certificates mes-1; users mes: job.submit, program.write"),
        "{summary}"
    );
    for secret in ["s3cret", "BEGIN", "MIIE"] {
        assert!(!summary.contains(secret), "{summary}");
        assert!(!cfg.to_toml_string().unwrap().contains(secret));
    }
    assert!(
        CellConfig::embedded_default()
            .summary()
            .contains("security: none")
    );
}

#[test]
fn security_mistakes_are_all_reported_with_their_keys() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().display().to_string();
    std::fs::write(dir.path().join("not-a-key.pem"), "hello").unwrap();
    let text = format!(
        "{MINIMAL}\n[bus]\nlisten = [\"tcp/127.0.0.1:7447\", \"tls/127.0.0.1:7448\"]\n\
         [security.tls]\nca = \"{d}/missing-ca.pem\"\ncertificate = \"{d}/not-a-key.pem\"\n\
         private_key = \"{d}/not-a-key.pem\"\n\
         [[security.roles]]\nname = \"mes\"\ncert_common_names = [\"mes-1\"]\n\
         permissions = [\"job.submit\", \"jobs.submit\"]\n\
         [[security.roles]]\nname = \"ops\"\nusernames = [\"ops\"]\npermissions = [\"io.do\"]\n\
         [[security.roles]]\nname = \"mes\"\npermissions = []\n"
    );
    let e = errors_of(&text);
    let has = |needle: &[&str]| {
        assert!(
            e.iter().any(|m| needle.iter().all(|n| m.contains(n))),
            "no error with {needle:?} in {e:#?}"
        )
    };
    has(&["bus.listen[1]", "tcp/127.0.0.1:7447", "tls/127.0.0.1:7447"]);
    has(&["security.tls.ca", "missing-ca.pem", "cannot read it"]);
    has(&[
        "security.tls.certificate",
        "not-a-key.pem",
        "PEM certificate",
    ]);
    has(&["security.tls.private_key", "PEM private key"]);
    has(&[
        "security.roles.mes.permissions[2]",
        "\"jobs.submit\"",
        "job.submit, job.cancel",
    ]);
    has(&["security.roles.ops.usernames", "users_file"]);
    has(&["security.roles[3].name", "same name"]);
    has(&["security.roles[3].cert_common_names", "missing"]);
    has(&["security.roles[3].permissions", "missing"]);
    assert_eq!(e.len(), 9, "{e:#?}");
    assert!(
        !e.iter().any(|m| m.contains("hello")),
        "file content leaked: {e:#?}"
    );
}

#[test]
fn roles_need_something_that_identifies_clients() {
    let dir = tempfile::tempdir().unwrap();
    let role = "[[security.roles]]\nname = \"dash\"\ncert_common_names = [\"d\"]\n\
                permissions = [\"status.read\"]\n";
    // No TLS at all.
    let e = errors_of(&format!("{MINIMAL}\n{role}"));
    assert_eq!(e.len(), 1, "{e:?}");
    assert!(e[0].contains("only over TLS"), "{e:?}");
    // TLS without client certificates.
    let text = secured(
        dir.path(),
        &format!("{TLS}require_client_certificates = false\n{role}"),
    );
    let e = errors_of(&text);
    assert_eq!(e.len(), 1, "{e:?}");
    assert!(
        e[0].contains("require_client_certificates = false"),
        "{e:?}"
    );
    // A user the users file lacks; a malformed line, named by number only.
    std::fs::write(dir.path().join("bad-users.txt"), "mes:pw\nnocolon\n").unwrap();
    let text = format!(
        "{MINIMAL}\n[security]\nusers_file = \"{}/bad-users.txt\"\n\
         [[security.roles]]\nname = \"x\"\nusernames = [\"bob\"]\npermissions = [\"io.do\"]\n",
        dir.path().display()
    );
    let e = errors_of(&text);
    assert_eq!(e.len(), 2, "{e:?}");
    assert!(
        e[0].contains("line 2") && !e[0].contains("nocolon"),
        "{e:?}"
    );
    assert!(
        e[1].contains("usernames[1]") && e[1].contains("\"bob\""),
        "{e:?}"
    );
}

#[test]
fn a_journal_inside_the_library_and_fetches_from_cellgate_keys_are_refused() {
    let f = |programs: &str| format!("cell = \"c\"\n[programs]\ndir = \"lib\"\n{programs}\n");
    let e = errors_of(&f("journal = \"lib/j\""));
    assert!(
        e[0].starts_with("programs.journal = \"lib/j\": must lie outside programs.dir"),
        "{e:?}"
    );
    assert!(errors_of(&f("journal = \"jobs\"")).is_empty());
    assert!(errors_of(&f("journal = \"lib/.journal\"")).is_empty());
    let e = errors_of(&f(
        "fetch_prefixes = [\"cellgate\", \"cellgate/c/program\", \"cam/*\"]",
    ));
    assert_eq!(e.len(), 3, "{e:?}");
    assert!(e.iter().any(|m| m.contains("overlaps bus.prefix")), "{e:?}");
    assert!(e.iter().any(|m| m.contains("plain chunks")), "{e:?}");
    assert!(errors_of(&f("fetch_prefixes = [\"cam/programs\"]")).is_empty());
}

#[test]
fn a_listener_beyond_loopback_without_security_is_warned_of() {
    let cell = |listen: &str| {
        CellConfig::from_toml_str(
            &format!("cell = \"c\"\n[bus]\nlisten = [\"{listen}\"]\n"),
            "t",
        )
        .unwrap()
    };
    for ep in [
        "tcp/127.0.0.1:7447",
        "tcp/[::1]:7447",
        "tcp/localhost:7447",
        "unixsock-stream//tmp/z",
    ] {
        assert!(cell(ep).warnings().is_empty(), "{ep}");
    }
    for ep in ["tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/10.1.3.20:7447"] {
        let w = cell(ep).warnings();
        assert_eq!(w.len(), 1, "{ep}");
        assert!(w[0].contains("no [security]"), "{w:?}");
    }
}

#[test]
fn every_unknown_key_is_reported_at_once_with_the_key_it_most_likely_means() {
    let text = "cell = \"c\"\n[bus]\nlisen = [\"tcp/127.0.0.1:1\"]\n[[machines]]\nname = \"m\"\n\
                protocl = \"a\"\ntransport = { kind = \"sim\" }\n[telemetri]\nx = 1\n";
    let e = errors_of(text);
    assert!(
        e[0].starts_with("test.toml:3: unknown key `lisen` (did you mean `listen`?)"),
        "{e:?}"
    );
    assert!(
        e[1].starts_with("test.toml:6: unknown key `protocl` (did you mean `protocol`?)"),
        "{e:?}"
    );
    assert!(
        e[2].starts_with("test.toml:8: unknown key `telemetri` (did you mean `telemetry`?)"),
        "{e:?}"
    );
    // And the errors past the unknown keys: the machine's protocol is missing.
    assert!(
        e.iter().any(|m| m.contains("machines.m.protocol: missing")),
        "{e:?}"
    );
    // A key far from every known one gets no suggestion.
    let e = errors_of("cell = \"c\"\nzzzzzzzz = 1\n");
    assert!(!e[0].contains("did you mean"), "{e:?}");
}

#[test]
fn a_g05_tables_unknown_keys_are_reported_with_their_lines_and_the_tables_keys() {
    // The table holds the engine's format and the stream's own keys side by side: a typo in
    // either is found at its line, with every key the table takes.
    let text = "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n\
                transport = { kind = \"sim\" }\n[machines.g05]\naxes = 3\nunit_time = 8\n\
                idle = 100\n";
    let e = errors_of(text);
    assert!(
        e[0].starts_with("test.toml:8: unknown key `unit_time` (did you mean `unit_time_ms`?)"),
        "{e:?}"
    );
    assert!(
        e[1].starts_with("test.toml:9: unknown key `idle` (did you mean `idle_ms`?)"),
        "{e:?}"
    );
    for key in ["`axes`", "`aux_order`", "`before`", "`idle_ms`"] {
        assert!(e[0].contains(key), "{key}: {e:?}");
    }
    // `axes` alone has no default (parameter 7635 has none that fits every CNC).
    let e = errors_of(&text.replace("axes = 3\n", ""));
    assert!(
        e.iter().any(|m| m.contains("missing field `axes`")),
        "{e:?}"
    );
    // A value of the wrong type is named with its key.
    let e = errors_of(
        &text
            .replace("unit_time = 8", "unit_time_ms = 3")
            .replace("idle = 100", ""),
    );
    assert!(e.iter().any(|m| m.contains("7618")), "{e:?}");
}

#[test]
fn the_gateways_own_files_are_refused_where_the_library_would_list_them() {
    let f = |extra: &str| format!("cell = \"c\"\n{extra}\n[programs]\ndir = \"lib\"\n");
    // The journal in the library's folder itself: the library would serve `jobs.redb`.
    for journal in ["lib", "./lib", "lib/", "lib/jobs"] {
        let e = errors_of(&format!("{}journal = {journal:?}\n", f("")));
        assert!(
            e.iter().any(|m| m.starts_with("programs.journal")
                && m.contains("must lie outside programs.dir")),
            "{journal}: {e:?}"
        );
    }
    let e = errors_of(&f("[history]\ndir = \"lib\""));
    assert!(e.iter().any(|m| m.starts_with("history.dir")), "{e:?}");
    let e = errors_of(&f("[bus]\nzenoh_config = \"lib/zenoh.json5\""));
    assert!(e.iter().any(|m| m.starts_with("bus.zenoh_config")), "{e:?}");
    // Hidden entries, and places beside the library, are fine.
    assert!(errors_of(&format!("{}journal = \"lib/.journal\"\n", f(""))).is_empty());
    assert!(errors_of(&f("[history]\ndir = \"lib/.history\"")).is_empty());
}

#[test]
fn a_cell_file_inside_the_library_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let lib = dir.path().join("lib");
    std::fs::create_dir(&lib).unwrap();
    let text = format!("cell = \"c\"\n[programs]\ndir = {lib:?}\n");
    std::fs::write(lib.join("cell.toml"), &text).unwrap();
    let e = CellConfig::load(&lib.join("cell.toml")).unwrap_err();
    assert!(e.to_string().contains("holds the cell file"), "{e}");
    std::fs::write(dir.path().join("cell.toml"), &text).unwrap();
    assert!(CellConfig::load(&dir.path().join("cell.toml")).is_ok());
}

#[test]
fn a_misspelt_protocol_does_not_hide_a_wrong_baud_rate() {
    let e = errors_of(
        "cell = \"c\"\n[[machines]]\nname = \"m1\"\nprotocl = \"a\"\n\
         transport = { kind = \"sim\", line = { baud = 12345 } }\n",
    );
    assert!(e.iter().any(|m| m.contains("protocl")), "{e:?}");
    assert!(e.iter().any(|m| m.contains("line.baud = 12345")), "{e:?}");
}

#[test]
fn mtconnect_takes_addresses_and_a_bounded_buffer() {
    let with = |section: &str| format!("{MINIMAL}\n[mtconnect]\n{section}\n");
    let cfg = CellConfig::from_toml_str(&with(""), "t").unwrap();
    assert_eq!(cfg.mtconnect, Some(MtconnectConfig::default()));
    assert!(cfg.warnings().is_empty(), "{:?}", cfg.warnings());
    let e = errors_of(&with(
        "listen = \"localhost\"\nbuffer_size = 10\nshdr_listen = \"x\"",
    ));
    assert_eq!(e.len(), 3, "{e:?}");
    assert!(e[0].contains("mtconnect.listen"), "{e:?}");
    assert!(e[1].contains("mtconnect.shdr_listen"), "{e:?}");
    assert!(e[2].contains("mtconnect.buffer_size"), "{e:?}");
    // Beyond loopback: allowed (it only reads), and warned of.
    let cfg = CellConfig::from_toml_str(&with("listen = \"0.0.0.0:5000\""), "t").unwrap();
    assert!(
        cfg.warnings()
            .iter()
            .any(|w| w.contains("mtconnect.listen")),
        "{:?}",
        cfg.warnings()
    );
    let back = CellConfig::from_toml_str(&cfg.to_toml_string().unwrap(), "t").unwrap();
    assert_eq!(back.mtconnect, cfg.mtconnect);
    // An SHDR port beyond loopback is warned of by its own name (its protocol has no login).
    let cfg = CellConfig::from_toml_str(&with("shdr_listen = \"0.0.0.0:7878\""), "t").unwrap();
    let w = cfg.warnings();
    assert!(
        w.len() == 1 && w[0].contains("mtconnect.shdr_listen") && w[0].contains("no login"),
        "{w:?}"
    );
}
