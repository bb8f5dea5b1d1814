use super::*;

#[test]
fn keys_are_built_and_read_back() {
    let k = CellKeys::new("cellgate", "line-3").unwrap();
    assert_eq!(k.machine("mill-1"), "cellgate/line-3/machine/mill-1");
    assert_eq!(
        k.leaf("mill-1", MachineLeaf::Status),
        "cellgate/line-3/machine/mill-1/status"
    );
    assert_eq!(
        k.job_events("mill-1", "mill-1-t0-7"),
        "cellgate/line-3/machine/mill-1/job/mill-1-t0-7"
    );
    assert_eq!(k.program("O1234"), "cellgate/line-3/program/O1234");
    assert_eq!(k.any_leaf(MachineLeaf::Do), "cellgate/line-3/machine/*/do");
    for leaf in MachineLeaf::ALL {
        let key = k.leaf("m", leaf);
        assert_eq!(k.parse(&key), Some(CellKey::Leaf { machine: "m", leaf }));
    }
    assert_eq!(
        k.parse(&k.job_events("m", "j")),
        Some(CellKey::JobEvents {
            machine: "m",
            job: "j"
        })
    );
    assert_eq!(
        k.parse(&k.program("p")),
        Some(CellKey::Program { name: "p" })
    );
    assert_eq!(
        k.parse(&k.machine("m")),
        Some(CellKey::Machine { machine: "m" })
    );
    assert_eq!(k.gateway(), "cellgate/line-3/gateway");
    assert_eq!(k.admin(), "cellgate/line-3/@admin");
    assert_eq!(k.parse(&k.gateway()), Some(CellKey::Gateway));
    assert_eq!(k.parse(&k.admin()), Some(CellKey::Admin));
    assert_eq!(k.reload(), "cellgate/line-3/@admin/reload");
    assert_eq!(k.parse(&k.reload()), Some(CellKey::Reload));
    assert_eq!(k.reloads(), "cellgate/line-3/reload");
    assert_eq!(k.parse(&k.reloads()), Some(CellKey::Reloaded));
    assert_eq!(cell_of_admin_key("cellgate", &k.reload()), None);
    assert_eq!(admin_selector("cellgate", "*"), "cellgate/*/@admin");
    assert_eq!(
        cell_of_admin_key("cellgate", "cellgate/line-3/@admin"),
        Some("line-3")
    );
    assert_eq!(cell_of_admin_key("cellgate", "cellgate/a/b/@admin"), None);
    assert_eq!(cell_of_admin_key("cellgate", "other/line-3/@admin"), None);
    for part in [G05Part::Status, G05Part::Blocks, G05Part::Producer] {
        let key = k.g05("m", "s1", part);
        assert_eq!(
            k.parse(&key),
            Some(CellKey::G05 {
                machine: "m",
                stream: "s1",
                part
            })
        );
    }
    assert_eq!(
        k.g05("m", "s1", G05Part::Blocks),
        "cellgate/line-3/machine/m/g05/s1/blocks"
    );
    assert_eq!(
        k.plc_message_send("plc-1"),
        "cellgate/line-3/plc/plc-1/message/send"
    );
    assert_eq!(
        k.parse_plc(&k.plc_message("plc-1")),
        Some(PlcKey::Message {
            plc: "plc-1",
            send: false
        })
    );
    assert_eq!(
        k.parse_plc(&k.plc_message_send("plc-1")),
        Some(PlcKey::Message {
            plc: "plc-1",
            send: true
        })
    );
    assert_eq!(k.parse_plc("cellgate/line-3/plc/plc-1/message/other"), None);
    assert_eq!(k.parse("cellgate/line-3/machine/m/g05/s1/other"), None);
    assert_eq!(k.parse("cellgate/line-3/machine/m/nope"), None);
    assert_eq!(
        k.sim("mill-1", SimLeaf::Di),
        "cellgate/line-3/sim/mill-1/di"
    );
    assert_eq!(k.any_sim(), "cellgate/line-3/sim/*/*");
    for leaf in SimLeaf::ALL {
        let key = k.sim("m", leaf);
        assert_eq!(k.parse(&key), Some(CellKey::Sim { machine: "m", leaf }));
    }
    assert_eq!(k.parse("cellgate/line-3/sim/m/nope"), None);
    assert_eq!(k.parse("cellgate/line-30/program/p"), None);
    assert_eq!(k.parse("other/line-3/program/p"), None);
}

#[test]
fn wild_or_malformed_roots_are_refused() {
    assert!(CellKeys::new("cellgate", "*").is_err());
    assert!(CellKeys::new("a/**", "c").is_err());
    assert!(CellKeys::new("a//b", "c").is_err());
    assert!(CellKeys::new("a", "b/c").is_err());
    assert!(is_plain_chunk("mill-1"));
    assert!(!is_plain_chunk("a/b"));
    assert!(!is_plain_chunk("*"));
    assert!(!is_plain_chunk(""));
}
