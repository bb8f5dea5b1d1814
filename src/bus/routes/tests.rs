use super::*;

fn keys() -> CellKeys {
    CellKeys::new("cellgate", "demo").unwrap()
}

/// Every row of every table: its key, what arrives there, its pool and permission.
pub(crate) fn every_row(
    keys: &CellKeys,
) -> Vec<(String, Arrives, Option<Pool>, Option<Permission>)> {
    fn of<C>(routes: Vec<Route<C>>) -> Vec<(String, Arrives, Option<Pool>, Option<Permission>)> {
        routes
            .into_iter()
            .flat_map(|r| r.rows)
            .map(|r| (r.key, r.arrives, r.pool, r.permission))
            .collect()
    }
    let mut rows = of(cell(keys));
    rows.extend(of(vec![g05(keys)]));
    rows.extend(of(vec![sim(keys)]));
    rows.extend(of(plc(keys)));
    rows
}

#[test]
fn no_key_is_served_twice_the_same_way() {
    // Two queryables on one key would answer a get twice.
    let rows = every_row(&keys());
    let mut seen = std::collections::BTreeSet::new();
    for (key, arrives, _, _) in &rows {
        assert!(
            zenoh::key_expr::keyexpr::new(key.as_str()).is_ok(),
            "{key} is not a key expression"
        );
        let ways: &[bool] = match arrives {
            Arrives::Queries | Arrives::Writes(None) => &[true],
            Arrives::Samples(_) => &[false],
            Arrives::Writes(Some(_)) => &[true, false],
        };
        for queries in ways {
            assert!(seen.insert((key.clone(), *queries)), "{key} twice");
        }
    }
}

#[test]
fn only_misdirected_writes_have_no_permission() {
    // No role is meant to put on a read key: those rows alone name no permission, and hear
    // other sessions only (the gateway publishes on some of them itself).
    let misdirected = route_misdirected::read_keys(&keys());
    for (key, arrives, pool, permission) in every_row(&keys()) {
        if permission.is_none() {
            assert!(misdirected.contains(&key), "{key}");
            assert_eq!(arrives, Arrives::Samples(Locality::Remote), "{key}");
            assert_eq!(pool, Some(Pool::Read), "{key}");
        }
    }
}
