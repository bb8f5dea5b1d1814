use super::*;
use cellgate_core::config::Role;

const HERE: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);

fn security(users: &std::path::Path) -> SecurityConfig {
    SecurityConfig {
        tls: None,
        users_file: Some(users.to_path_buf()),
        roles: vec![
            Role {
                name: "operator".into(),
                cert_common_names: vec!["tablet-1".into()],
                usernames: vec!["olga".into()],
                permissions: vec![Permission::StatusRead, Permission::IoDo],
            },
            Role {
                name: "engineer".into(),
                cert_common_names: vec![],
                usernames: vec!["erik".into()],
                permissions: vec![Permission::ProgramWrite, Permission::ProgramRelease],
            },
        ],
    }
}

fn auth() -> (tempfile::TempDir, Auth) {
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("users");
    std::fs::write(&users, "olga:secret\nerik:other\nnobody:x\n").unwrap();
    let a = Auth::new(
        &security(&users),
        Duration::from_secs(60),
        Duration::from_secs(3600),
        4,
    );
    (dir, a)
}

#[test]
fn users_log_in_with_the_users_file_and_get_their_roles_permissions() {
    let (_d, a) = auth();
    assert!(a.secured());
    let (id, u, _) = a.login("olga", "secret", HERE, None).unwrap();
    assert!(u.may(Permission::IoDo) && u.may(Permission::StatusRead));
    assert!(!u.may(Permission::JobSubmit));
    assert_eq!(a.user(&id).unwrap().name, "olga");
    let (_, e, _) = a.login("erik", "other", HERE, None).unwrap();
    // Writing the library includes reading it.
    assert!(e.may(Permission::ProgramRead));
    assert_eq!(
        a.login("olga", "wrong", HERE, None).unwrap_err(),
        LoginError::Refused
    );
    assert_eq!(
        a.login("ghost", "", HERE, None).unwrap_err(),
        LoginError::Refused
    );
    assert_eq!(
        a.login("nobody", "x", HERE, None).unwrap_err(),
        LoginError::NoRole("nobody".into())
    );
    a.logout(&id);
    assert!(a.user(&id).is_none());
}

#[test]
fn a_certificate_logs_in_by_its_common_name_and_nobody_else_implicitly() {
    let (_d, a) = auth();
    assert!(a.implicit(None).is_none());
    assert!(a.implicit(Some("stranger")).is_none());
    let (_, u) = a.implicit(Some("tablet-1")).unwrap();
    assert_eq!(u.via, "certificate");
    assert!(u.may(Permission::IoDo));
}

#[test]
fn without_security_everybody_may_everything() {
    let a = Auth::new(
        &SecurityConfig::default(),
        Duration::from_secs(60),
        Duration::from_secs(60),
        4,
    );
    assert!(!a.secured());
    let (_, u) = a.implicit(None).unwrap();
    assert!(Permission::ALL.iter().all(|p| u.may(*p)));
}

#[test]
fn sessions_end_when_idle_and_csrf_must_match() {
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("users");
    std::fs::write(&users, "olga:secret\n").unwrap();
    let a = Auth::new(
        &security(&users),
        Duration::from_millis(50),
        Duration::from_secs(60),
        4,
    );
    let (id, u, _) = a.login("olga", "secret", HERE, None).unwrap();
    assert!(Auth::csrf_ok(&u, Some(&u.csrf)));
    assert!(!Auth::csrf_ok(&u, Some("forged")));
    assert!(!Auth::csrf_ok(&u, None));
    std::thread::sleep(Duration::from_millis(80));
    assert!(a.user(&id).is_none(), "idle too long");
}

#[test]
fn a_users_new_session_ends_that_users_oldest_and_nobody_elses() {
    let (_d, a) = auth();
    let (erik, erik_user, _) = a.login("erik", "other", HERE, None).unwrap();
    let mut olga = Vec::new();
    for _ in 0..4 {
        olga.push(a.login("olga", "secret", HERE, None).unwrap());
    }
    // Many more logins of olga: each ends her oldest session.
    for _ in 0..50 {
        let oldest = olga.remove(0);
        olga.push(a.login("olga", "secret", HERE, None).unwrap());
        assert!(a.user(&oldest.0).is_none());
        assert!(oldest.1.ended.is_cancelled(), "its event streams end");
    }
    assert!(olga.iter().all(|(id, _, _)| a.user(id).is_some()));
    assert_eq!(a.user(&erik).unwrap().name, "erik");
    assert!(!erik_user.ended.is_cancelled());
}

#[test]
fn logout_and_expiry_end_the_sessions_token() {
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("users");
    std::fs::write(&users, "olga:secret\n").unwrap();
    let a = Auth::new(
        &security(&users),
        Duration::from_millis(50),
        Duration::from_secs(60),
        4,
    );
    let (id, u, _) = a.login("olga", "secret", HERE, None).unwrap();
    assert!(a.live(&id));
    a.logout(&id);
    assert!(u.ended.is_cancelled() && !a.live(&id));
    let (id, u, _) = a.login("olga", "secret", HERE, None).unwrap();
    std::thread::sleep(Duration::from_millis(80));
    assert!(!a.live(&id), "idle too long");
    assert!(a.user(&id).is_none());
    assert!(u.ended.is_cancelled());
}

#[test]
fn guessing_a_password_is_throttled_and_the_right_one_waits_its_turn() {
    let (_d, a) = auth();
    for _ in 0..crate::console::throttle::FREE_PER_USER {
        assert_eq!(
            a.login("olga", "guess", HERE, None).unwrap_err(),
            LoginError::Refused
        );
    }
    let LoginError::Throttled(wait) = a.login("olga", "guess", HERE, None).unwrap_err() else {
        panic!("not throttled");
    };
    assert_eq!(wait, Duration::from_secs(1));
    // The right password is not looked at while the name is closed.
    assert!(matches!(
        a.login("olga", "secret", HERE, None).unwrap_err(),
        LoginError::Throttled(_)
    ));
    std::thread::sleep(wait + Duration::from_millis(20));
    assert_eq!(
        a.login("olga", "secret", HERE, None).unwrap().1.name,
        "olga"
    );
}

#[test]
fn a_reload_ends_the_sessions_of_users_whose_roles_changed() {
    let (d, a) = auth();
    let (olga, olga_user, _) = a.login("olga", "secret", HERE, None).unwrap();
    let (erik, erik_user, _) = a.login("erik", "other", HERE, None).unwrap();
    let mut changed = security(&d.path().join("users"));
    changed.roles[0].permissions.push(Permission::JobSubmit);
    assert_eq!(a.set_security(&changed), 1);
    assert!(olga_user.ended.is_cancelled() && a.user(&olga).is_none());
    assert!(!erik_user.ended.is_cancelled() && a.user(&erik).is_some());
    // A user removed from the users file.
    std::fs::write(d.path().join("users"), "olga:secret\n").unwrap();
    assert_eq!(a.set_security(&changed), 1);
    assert!(erik_user.ended.is_cancelled());
    assert!(a.login("erik", "other", HERE, None).is_err());
}
