use super::*;
use cellgate_core::config::Role;
use zenoh::key_expr::keyexpr;

fn role(name: &str, cn: &str, permissions: &[Permission]) -> Role {
    Role {
        name: name.to_string(),
        cert_common_names: vec![cn.to_string()],
        usernames: Vec::new(),
        permissions: permissions.to_vec(),
    }
}

fn security(roles: Vec<Role>) -> SecurityConfig {
    SecurityConfig {
        roles,
        ..SecurityConfig::default()
    }
}

/// Whether `acl` lets the holder of `cn` send (`Ingress`) or receive (`Egress`) `message`
/// on `key`, by zenoh's rule: some allow rule of the subject's policies includes the key.
fn allows(acl: &Value, cn: &str, flow: Flow, message: &str, key: &str) -> bool {
    let key = keyexpr::new(key).unwrap();
    let subjects: Vec<&str> = acl["subjects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|s| {
            s["cert_common_names"]
                .as_array()
                .is_some_and(|c| c.iter().any(|c| c == cn))
        })
        .map(|s| s["id"].as_str().unwrap())
        .collect();
    let rule_ids: Vec<&str> = acl["policies"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| {
            p["subjects"]
                .as_array()
                .unwrap()
                .iter()
                .any(|s| subjects.contains(&s.as_str().unwrap()))
        })
        .flat_map(|p| p["rules"].as_array().unwrap().iter())
        .map(|r| r.as_str().unwrap())
        .collect();
    acl["rules"].as_array().unwrap().iter().any(|r| {
        rule_ids.contains(&r["id"].as_str().unwrap())
            && r["flows"]
                .as_array()
                .unwrap()
                .iter()
                .any(|f| f == flow.name())
            && r["messages"]
                .as_array()
                .unwrap()
                .iter()
                .any(|m| m == message)
            && r["key_exprs"]
                .as_array()
                .unwrap()
                .iter()
                .any(|k| keyexpr::new(k.as_str().unwrap()).unwrap().includes(key))
    })
}

fn cell_acl() -> (Value, CellKeys) {
    let keys = CellKeys::new("cellgate", "c").unwrap();
    let sec = security(vec![
        role("dashboard", "dash", &[Permission::StatusRead]),
        role(
            "mes",
            "mes",
            &[Permission::JobSubmit, Permission::ProgramWrite],
        ),
        role(
            "operator",
            "op",
            &[Permission::IoDo, Permission::JobCancel, Permission::PlcTag],
        ),
        role("admin", "adm", &[Permission::AdminRead]),
    ]);
    (access_control(&sec, &keys, "cellgate").unwrap(), keys)
}

#[test]
fn no_roles_no_access_control() {
    let keys = CellKeys::new("cellgate", "c").unwrap();
    assert!(access_control(&SecurityConfig::default(), &keys, "cellgate").is_none());
}

#[test]
fn the_generated_section_is_one_zenoh_accepts() {
    let (acl, _) = cell_acl();
    let mut config = zenoh::Config::default();
    config
        .insert_json5("access_control", &acl.to_string())
        .unwrap();
    assert_eq!(
        config
            .get_json("access_control/default_permission")
            .unwrap(),
        "\"deny\""
    );
}

#[test]
fn a_dashboard_reads_and_writes_nothing() {
    let (acl, k) = cell_acl();
    let status = k.leaf("m1", MachineLeaf::Status);
    assert!(allows(&acl, "dash", Flow::Ingress, "query", &status));
    assert!(allows(&acl, "dash", Flow::Egress, "reply", &status));
    assert!(allows(
        &acl,
        "dash",
        Flow::Ingress,
        "query",
        &k.any_leaf(MachineLeaf::Status)
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Ingress,
        "declare_subscriber",
        &k.all()
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Egress,
        "put",
        &k.job_events("m1", "j")
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Egress,
        "liveliness_token",
        &k.gateway()
    ));
    for (message, key) in [
        ("query", k.leaf("m1", MachineLeaf::Submit)),
        ("query", k.any_leaf(MachineLeaf::Submit)),
        ("query", k.leaf("m1", MachineLeaf::Do)),
        ("put", k.leaf("m1", MachineLeaf::Do)),
        ("query", k.program("O1")),
        ("query", k.program_write("O1")),
        ("put", k.program_write("O1")),
        ("delete", k.program_write("O1")),
        ("delete", k.job_events("m1", "j")),
        ("query", k.admin()),
        ("query", k.all()),
        ("query", k.plc_tag_set("plc-1", "door")),
        ("put", k.plc_tag_set("plc-1", "door")),
        ("put", k.plc_tag("plc-1", "door")),
    ] {
        assert!(
            !allows(&acl, "dash", Flow::Ingress, message, &key),
            "{message} on {key}"
        );
    }
    // The queue, a PLC link's status and its tags may be read: their writes have keys of
    // their own. Memory and transfers may not.
    assert!(allows(
        &acl,
        "dash",
        Flow::Ingress,
        "query",
        &k.leaf("m1", MachineLeaf::Job)
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Ingress,
        "query",
        &k.plc_tag("plc-1", "door")
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Ingress,
        "query",
        &k.any_plc_tag()
    ));
    let plc_status = k.plc_status("plc-1");
    assert!(allows(&acl, "dash", Flow::Ingress, "query", &plc_status));
    assert!(allows(&acl, "dash", Flow::Egress, "reply", &plc_status));
    assert!(allows(
        &acl,
        "dash",
        Flow::Egress,
        "declare_queryable",
        &plc_status
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Ingress,
        "query",
        &k.any_plc_status()
    ));
    for key in [
        k.plc_tag_set("plc-1", "door"),
        k.plc_mem("plc-1", 0, "D", Some(0)),
        k.plc_mem_write("plc-1", 0, "D", Some(0)),
        k.plc_transfer_send("plc-1", 1),
        k.plc_message_send("plc-1"),
    ] {
        assert!(
            !allows(&acl, "dash", Flow::Ingress, "query", &key),
            "query on {key}"
        );
    }
    // A dashboard sees DO outputs go out; the library's changes are for those who read it.
    let out = k.do_out("m1");
    let changed = k.program_changed("O1");
    assert!(allows(&acl, "dash", Flow::Egress, "put", &out));
    assert!(!allows(&acl, "dash", Flow::Egress, "put", &changed));
    assert!(allows(
        &acl,
        "mes",
        Flow::Ingress,
        "declare_subscriber",
        &changed
    ));
    assert!(allows(&acl, "mes", Flow::Egress, "put", &changed));
    // The gateway does not announce the routes a dashboard may not use.
    assert!(!allows(
        &acl,
        "dash",
        Flow::Egress,
        "declare_queryable",
        &k.leaf("m1", MachineLeaf::Submit)
    ));
}

#[test]
fn each_role_gets_its_routes_only() {
    let (acl, k) = cell_acl();
    let job = k.leaf("m1", MachineLeaf::Submit);
    assert!(allows(&acl, "mes", Flow::Ingress, "query", &job));
    assert!(allows(
        &acl,
        "mes",
        Flow::Ingress,
        "query",
        &k.program("O1")
    ));
    assert!(allows(
        &acl,
        "mes",
        Flow::Ingress,
        "put",
        &k.program_write("O1")
    ));
    assert!(allows(
        &acl,
        "mes",
        Flow::Ingress,
        "query",
        &k.program_write("O1")
    ));
    // The read key takes no write, even for a writer.
    assert!(!allows(&acl, "mes", Flow::Ingress, "put", &k.program("O1")));
    assert!(allows(
        &acl,
        "mes",
        Flow::Ingress,
        "declare_subscriber",
        &k.job_events("m1", "*")
    ));
    assert!(!allows(
        &acl,
        "mes",
        Flow::Ingress,
        "put",
        &k.leaf("m1", MachineLeaf::Do)
    ));
    assert!(!allows(
        &acl,
        "mes",
        Flow::Ingress,
        "delete",
        &k.job_events("m1", "j")
    ));
    assert!(allows(
        &acl,
        "op",
        Flow::Ingress,
        "put",
        &k.leaf("m1", MachineLeaf::Do)
    ));
    assert!(allows(
        &acl,
        "op",
        Flow::Ingress,
        "delete",
        &k.job_events("m1", "j")
    ));
    assert!(allows(
        &acl,
        "op",
        Flow::Ingress,
        "put",
        "cellgate/c/plc/plc-1/tag/door/set"
    ));
    assert!(!allows(
        &acl,
        "op",
        Flow::Ingress,
        "put",
        "cellgate/c/plc/plc-1/tag/door"
    ));
    assert!(!allows(
        &acl,
        "op",
        Flow::Ingress,
        "put",
        "cellgate/c/plc/plc-1/mem/D/1"
    ));
    assert!(!allows(&acl, "op", Flow::Ingress, "query", &job));
    assert!(allows(&acl, "adm", Flow::Ingress, "query", &k.admin()));
    assert!(allows(
        &acl,
        "adm",
        Flow::Ingress,
        "query",
        "cellgate/*/@admin"
    ));
    assert!(allows(&acl, "adm", Flow::Egress, "reply", &k.admin()));
    assert!(!allows(
        &acl,
        "adm",
        Flow::Egress,
        "reply",
        "cellgate/other/@admin"
    ));
    assert!(!allows(
        &acl,
        "nobody",
        Flow::Ingress,
        "query",
        &k.leaf("m1", MachineLeaf::Status)
    ));
}

#[test]
fn a_router_lets_the_gateway_do_the_mirror_of_its_clients() {
    let keys = CellKeys::new("cellgate", "c").unwrap();
    let sec = security(vec![role("dashboard", "dash", &[Permission::StatusRead])]);
    let acl = router_access_control(&sec, &keys, "cellgate", &["gw".to_string()]);
    let status = keys.leaf("m1", MachineLeaf::Status);
    assert!(allows(
        &acl,
        "gw",
        Flow::Ingress,
        "declare_queryable",
        &status
    ));
    assert!(allows(&acl, "gw", Flow::Ingress, "reply", &status));
    assert!(allows(&acl, "gw", Flow::Egress, "query", &status));
    assert!(allows(
        &acl,
        "gw",
        Flow::Egress,
        "put",
        &keys.leaf("m1", MachineLeaf::Do)
    ));
    assert!(allows(
        &acl,
        "gw",
        Flow::Ingress,
        "liveliness_token",
        &keys.gateway()
    ));
    assert!(allows(&acl, "dash", Flow::Ingress, "query", &status));
    let mut config = zenoh::Config::default();
    config
        .insert_json5("access_control", &acl.to_string())
        .unwrap();
}

#[test]
fn merging_keeps_the_files_rules_and_refuses_what_would_open_the_cell() {
    let (ours, _) = cell_acl();
    let theirs = json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": [{ "id": "mine", "messages": ["put"], "flows": ["ingress"],
                    "permission": "allow", "key_exprs": ["plant/**"] }],
        "subjects": [{ "id": "everyone" }],
        "policies": [{ "rules": ["mine"], "subjects": ["everyone"] }],
    });
    let merged = merge(&theirs, ours.clone()).unwrap();
    assert_eq!(merged["rules"][0]["id"], "mine");
    assert_eq!(
        merged["rules"].as_array().unwrap().len(),
        ours["rules"].as_array().unwrap().len() + 1
    );
    assert_eq!(merged["default_permission"], "deny");

    let mut open = theirs.clone();
    open["default_permission"] = json!("allow");
    assert_eq!(merge(&open, ours.clone()), Err(AclError::DefaultAllow));
    let mut clash = theirs;
    clash["subjects"][0]["id"] = json!("cellgate/role/x");
    assert!(matches!(
        merge(&clash, ours.clone()),
        Err(AclError::ReservedId {
            list: "subjects",
            ..
        })
    ));
    let disabled = json!({ "enabled": false, "default_permission": "allow",
                           "rules": null, "subjects": null, "policies": null });
    assert_eq!(merge(&disabled, ours.clone()).unwrap(), ours);
}

/// `plc.transfer` sends transfers (mode 1) and non-procedure messages (modes 4–5) and nothing
/// else; the PLC's messages reach a subscriber with `status.read`.
#[test]
fn plc_transfer_sends_transfers_and_messages() {
    let keys = CellKeys::new("cellgate", "c").unwrap();
    let sec = security(vec![
        role("sender", "snd", &[Permission::PlcTransfer]),
        role("dashboard", "dash", &[Permission::StatusRead]),
    ]);
    let acl = access_control(&sec, &keys, "cellgate").unwrap();
    for key in [
        keys.plc_transfer_send("plc-1", 1),
        keys.plc_message_send("plc-1"),
    ] {
        assert!(allows(&acl, "snd", Flow::Ingress, "query", &key), "{key}");
        assert!(allows(&acl, "snd", Flow::Ingress, "put", &key), "{key}");
        assert!(!allows(&acl, "dash", Flow::Ingress, "put", &key), "{key}");
    }
    assert!(!allows(
        &acl,
        "snd",
        Flow::Ingress,
        "query",
        &keys.plc_mem("plc-1", 0, "D", Some(0))
    ));
    assert!(allows(
        &acl,
        "dash",
        Flow::Egress,
        "put",
        &keys.plc_message("plc-1")
    ));
}

#[test]
fn only_cell_reload_reloads_and_every_reader_sees_what_it_did() {
    let keys = CellKeys::new("cellgate", "c").unwrap();
    let sec = security(vec![
        role("dashboard", "dash", &[Permission::StatusRead]),
        role("admin", "adm", &[Permission::AdminRead]),
        role("engineer", "eng", &[Permission::CellReload]),
    ]);
    let acl = access_control(&sec, &keys, "cellgate").unwrap();
    let reload = keys.reload();
    assert!(allows(&acl, "eng", Flow::Ingress, "query", &reload));
    assert!(allows(&acl, "eng", Flow::Egress, "reply", &reload));
    for who in ["dash", "adm"] {
        assert!(!allows(&acl, who, Flow::Ingress, "query", &reload), "{who}");
    }
    // Reading the admin document is not reloading it, nor the other way round.
    assert!(!allows(&acl, "eng", Flow::Ingress, "query", &keys.admin()));
    assert!(allows(&acl, "dash", Flow::Egress, "put", &keys.reloads()));
    assert!(!allows(&acl, "eng", Flow::Egress, "put", &keys.reloads()));
}

/// Every row of the route table is reachable through the rules of the permission it names:
/// a client's get (or put or delete) comes in, and the gateway's queryable (or subscriber)
/// and its replies go out; so the table and the rules cannot drift apart.
#[test]
fn every_route_is_granted_by_its_permission() {
    use super::super::routes::{Arrives, tests::every_row};
    let keys = CellKeys::new("cellgate", "demo").unwrap();
    let rows = every_row(&keys);
    assert!(rows.len() > 30, "{}", rows.len());
    for (key, arrives, _, permission) in rows {
        let Some(p) = permission else { continue };
        let rules = grants(p, &keys, "cellgate");
        let allows = |flow: Flow, message: &str| {
            rules.iter().any(|g| {
                g.flow == flow
                    && g.messages.contains(&message)
                    && g.keys.iter().any(|k| {
                        keyexpr::new(k.as_str())
                            .unwrap()
                            .includes(keyexpr::new(key.as_str()).unwrap())
                    })
            })
        };
        const QUERIES: (&[&str], &[&str]) = (&["query"], &["declare_queryable", "reply"]);
        const SAMPLES: (&[&str], &[&str]) = (&["put", "delete"], &["declare_subscriber"]);
        let ways: &[(&[&str], &[&str])] = match arrives {
            Arrives::Queries | Arrives::Writes(None) => &[QUERIES],
            Arrives::Samples(_) => &[SAMPLES],
            Arrives::Writes(Some(_)) => &[QUERIES, SAMPLES],
        };
        for (sent, served) in ways {
            assert!(
                sent.iter().any(|m| allows(Flow::Ingress, m)),
                "{key}: {} lets no client send {sent:?} there",
                p.name()
            );
            for m in *served {
                assert!(
                    allows(Flow::Egress, m),
                    "{key}: {} does not let the gateway send {m} there",
                    p.name()
                );
            }
        }
    }
}
