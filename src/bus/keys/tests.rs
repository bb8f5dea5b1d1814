use super::*;

#[test]
fn every_built_key_is_a_valid_key_expression() {
    let k = CellKeys::new("factory/a", "c1").unwrap();
    let keys = [
        k.machine("m"),
        k.leaf("m", MachineLeaf::Alarm),
        k.job_events("m", "m-x-1"),
        k.program("O1.nc"),
        k.any_leaf(MachineLeaf::Status),
        k.any_job_events(),
        k.any_program(),
        k.gateway(),
        k.admin(),
        k.reload(),
        k.reloads(),
        k.all(),
        k.any_machine(),
        k.leaf("m", MachineLeaf::G05),
        k.g05("m", "s", G05Part::Blocks),
        k.any_g05(G05Part::Status),
        k.every_g05_key(),
        k.plc_area("plc-1", PlcArea::Tag),
        k.any_plc_area(PlcArea::Mem),
        k.any_plc(),
        gateway_selector("factory/a", "*"),
    ];
    for key in keys {
        assert!(keyexpr::new(key.as_str()).is_ok(), "{key}");
    }
}

#[test]
fn route_patterns_take_in_their_keys_and_no_others() {
    let k = CellKeys::new("cellgate", "c").unwrap();
    let includes = |pattern: &str, key: &str| {
        keyexpr::new(pattern)
            .unwrap()
            .includes(keyexpr::new(key).unwrap())
    };
    let g05 = k.every_g05_key();
    assert!(includes(&g05, &k.leaf("m1", MachineLeaf::G05)));
    assert!(includes(&g05, &k.g05("m1", "s-7", G05Part::Status)));
    assert!(includes(&g05, &k.g05("m1", "s-7", G05Part::Blocks)));
    assert!(includes(&g05, &k.g05("m1", "s-7", G05Part::Producer)));
    assert!(!includes(&g05, &k.leaf("m1", MachineLeaf::Do)));
    let tags = k.any_plc_area(PlcArea::Tag);
    assert!(includes(&tags, "cellgate/c/plc/plc-1/tag/door"));
    assert!(!includes(&tags, "cellgate/c/plc/plc-1/mem/D/100"));
    assert!(includes(&k.any_plc(), "cellgate/c/plc/plc-1/mem/D/100"));
    assert!(includes(&k.any_machine(), &k.machine("m1")));
    assert!(!includes(
        &k.any_machine(),
        &k.leaf("m1", MachineLeaf::Status)
    ));
    assert_eq!(gateway_selector("cellgate", "c"), k.gateway());
    assert_eq!(cell_of_gateway_key("cellgate", &k.gateway()), Some("c"));
    assert_eq!(
        cell_of_gateway_key("cellgate", "cellgate/a/b/gateway"),
        None
    );
}

#[test]
fn wildcard_queries_take_in_matching_keys() {
    let k = CellKeys::new("cellgate", "c").unwrap();
    let q = KeyExpr::new("cellgate/c/machine/*/status").unwrap();
    assert!(intersects(&q, &k.leaf("m1", MachineLeaf::Status)));
    assert!(!intersects(&q, &k.leaf("m1", MachineLeaf::Di)));
    let all = KeyExpr::new("cellgate/c/**").unwrap();
    assert!(intersects(&all, &k.program("p")));
}

#[test]
fn plain_chunks_are_what_zenoh_takes_as_one_chunk_without_wildcards() {
    for chunk in [
        "mill-1", "a b", "@admin", "O1234.nc", "x+y", "", "a/b", "*", "**", "$*", "a$*b", "a?",
        "a#", "ä", "-", ".", "..",
    ] {
        let zenoh = !chunk.contains('/') && keyexpr::new(chunk).is_ok_and(|k| !k.is_wild());
        assert_eq!(is_plain_chunk(chunk), zenoh, "{chunk:?}");
    }
}

#[test]
fn the_gateway_s_event_keys_read_back_and_no_route_takes_them_for_another() {
    let k = CellKeys::new("cellgate", "c").unwrap();
    let changed = k.program_changed("O1.nc");
    let out = k.do_out("m1");
    assert_eq!(changed, "cellgate/c/program/O1.nc/changed");
    assert_eq!(out, "cellgate/c/machine/m1/do/out");
    assert_eq!(k.parse_event(&changed), Some((true, "O1.nc")));
    assert_eq!(k.parse_event(&out), Some((false, "m1")));
    assert_eq!(k.parse_event(&k.program_write("O1.nc")), None);
    // Neither is a key of the grammar: no route of the gateway serves or takes them (the DO
    // route subscribes to `…/do` only, so the gateway's own event is not a DO command).
    assert_eq!(k.parse(&changed), None);
    assert_eq!(k.parse(&out), None);
    let includes = |pattern: &str, key: &str| {
        keyexpr::new(pattern)
            .unwrap()
            .includes(keyexpr::new(key).unwrap())
    };
    assert!(!includes(&k.any_leaf(MachineLeaf::Do), &out));
    assert!(!includes(&k.any_program_write(), &changed));
    for key in [&changed, &out] {
        assert!(keyexpr::new(key.as_str()).is_ok(), "{key}");
    }
}

#[test]
fn the_reload_key_is_reached_by_no_wildcard_of_the_cell() {
    let k = CellKeys::new("cellgate", "c").unwrap();
    let reload = k.reload();
    let reload = keyexpr::new(reload.as_str()).unwrap();
    for pattern in [
        k.all(),
        k.admin(),
        admin_selector("cellgate", "*"),
        "cellgate/**".to_string(),
    ] {
        let p = keyexpr::new(pattern.as_str()).unwrap();
        assert!(!p.intersects(reload), "{pattern} reaches {reload}");
    }
    // What each reload did is the cell's data: `P/C/**` takes it in.
    let (all, reloads) = (k.all(), k.reloads());
    let all = keyexpr::new(all.as_str()).unwrap();
    assert!(all.includes(keyexpr::new(reloads.as_str()).unwrap()));
}
