//! Who may open a session: the cell's users file and roles, as on the bus and the console.
//!
//! A cell without users takes anonymous sessions (its server listens on loopback unless told
//! otherwise, `check-config` warns). A cell with users refuses anonymous sessions and takes
//! a user name and password, checked and throttled as console logins are
//! ([`crate::console::auth::Auth::check`]); the user needs `status.read`. The password
//! travels encrypted: the token policy of every endpoint, the None one too, asks the client
//! to encrypt it with the server's certificate (Basic256Sha256, RSA-OAEP).

use std::net::{IpAddr, Ipv4Addr};
use std::sync::Arc;

use async_trait::async_trait;
use opcua::crypto::SecurityPolicy;
use opcua::server::authenticator::{
    AuthManager, Password, UserToken, user_pass_security_policy_id,
};
use opcua::server::{ANONYMOUS_USER_TOKEN_ID, ServerEndpoint};
use opcua::types::{Error, StatusCode, UAString, UserTokenPolicy, UserTokenType};

use crate::console::auth::{Auth, LoginError};
use cellgate_core::config::Permission;

/// The address OPC UA logins are throttled under: the stack does not tell the peer's, so
/// every OPC UA client counts as one address (and each user name as itself).
const OPCUA_PEER: IpAddr = IpAddr::V4(Ipv4Addr::UNSPECIFIED);

/// The policy id of the anonymous token.
const ANONYMOUS_POLICY: &str = "anonymous";

/// The server's gate.
pub struct Gate {
    /// Users and roles; `None`: a cell without users (anonymous sessions).
    pub auth: Option<Arc<Auth>>,
}

#[async_trait]
impl AuthManager for Gate {
    async fn authenticate_anonymous_token(&self, _endpoint: &ServerEndpoint) -> Result<(), Error> {
        if self.auth.is_none() {
            return Ok(());
        }
        Err(Error::new(
            StatusCode::BadIdentityTokenRejected,
            "this cell has users: log in with a user name and password",
        ))
    }

    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        let Some(auth) = &self.auth else {
            return Err(Error::new(
                StatusCode::BadIdentityTokenRejected,
                "this cell has no users file: connect anonymously",
            ));
        };
        match auth.check(username, password.get(), OPCUA_PEER) {
            Ok(p) if p.contains(&Permission::StatusRead) => {
                tracing::info!(user = %username, "opcua: session opened");
                Ok(UserToken(username.to_string()))
            }
            Ok(_) => Err(Error::new(
                StatusCode::BadUserAccessDenied,
                format!("user {username} holds no role with status.read"),
            )),
            Err(e) => {
                tracing::warn!(user = %username, error = %e, "opcua: login refused");
                let code = match e {
                    LoginError::NoRole(_) => StatusCode::BadUserAccessDenied,
                    _ => StatusCode::BadIdentityTokenRejected,
                };
                Err(Error::new(code, e.to_string()))
            }
        }
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        if self.auth.is_none() {
            return vec![UserTokenPolicy {
                policy_id: UAString::from(ANONYMOUS_POLICY),
                token_type: UserTokenType::Anonymous,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            }];
        }
        // On the None endpoint the token policy itself names the policy that encrypts the
        // password (Part 4 §7.41): it never travels in clear.
        let uri = if endpoint.security_policy() == SecurityPolicy::None {
            UAString::from(SecurityPolicy::Basic256Sha256.to_uri())
        } else {
            UAString::null()
        };
        vec![UserTokenPolicy {
            policy_id: user_pass_security_policy_id(endpoint),
            token_type: UserTokenType::UserName,
            issued_token_type: UAString::null(),
            issuer_endpoint_url: UAString::null(),
            security_policy_uri: uri,
        }]
    }
}

/// Whether sessions need a user: on any cell with `[security]`. A cell secured with TLS and
/// certificate roles alone has no users for the server to check, so it takes nobody rather
/// than anybody.
pub fn secured(security: &cellgate_core::config::SecurityConfig) -> bool {
    security.tls.is_some() || security.users_file.is_some()
}

/// The user token ids endpoints list (the gate decides; the list only must not be empty).
pub fn token_ids() -> Vec<String> {
    vec![ANONYMOUS_USER_TOKEN_ID.to_string()]
}

#[cfg(test)]
mod tests {
    use cellgate_core::config::{SecurityConfig, TlsConfig};

    #[test]
    fn a_cell_with_tls_and_no_users_takes_nobody_anonymously() {
        assert!(!super::secured(&SecurityConfig::default()));
        let tls_only = SecurityConfig {
            tls: Some(TlsConfig {
                ca: "ca.pem".into(),
                certificate: "c.pem".into(),
                private_key: "k.pem".into(),
                require_client_certificates: true,
                verify_name_on_connect: true,
            }),
            ..SecurityConfig::default()
        };
        assert!(super::secured(&tls_only));
    }
}
