use super::*;
use cellgate_core::config::Role;

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
    );
    (dir, a)
}

#[test]
fn users_log_in_with_the_users_file_and_get_their_roles_permissions() {
    let (_d, a) = auth();
    assert!(a.secured());
    let (id, u) = a.login("olga", "secret").unwrap();
    assert!(u.may(Permission::IoDo) && u.may(Permission::StatusRead));
    assert!(!u.may(Permission::JobSubmit));
    assert_eq!(a.user(&id).unwrap().name, "olga");
    let (_, e) = a.login("erik", "other").unwrap();
    // Writing the library includes reading it.
    assert!(e.may(Permission::ProgramRead));
    assert_eq!(a.login("olga", "wrong").unwrap_err(), LoginError::Refused);
    assert_eq!(a.login("ghost", "").unwrap_err(), LoginError::Refused);
    assert_eq!(
        a.login("nobody", "x").unwrap_err(),
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
    );
    let (id, u) = a.login("olga", "secret").unwrap();
    assert!(Auth::csrf_ok(&u, Some(&u.csrf)));
    assert!(!Auth::csrf_ok(&u, Some("forged")));
    assert!(!Auth::csrf_ok(&u, None));
    std::thread::sleep(Duration::from_millis(80));
    assert!(a.user(&id).is_none(), "idle too long");
}
