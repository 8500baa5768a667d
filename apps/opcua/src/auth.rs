//! Who may open a session and who may write: anonymous sessions where
//! allowed (a loopback OPCUA_HOST, or OPCUA_ANONYMOUS = Yes), users of
//! OPCUA_USERS by name and password. Only users of role `write` write.

use std::sync::Arc;

use async_trait::async_trait;
use opcua::crypto::SecurityPolicy;
use opcua::server::address_space::AccessLevel;
use opcua::server::authenticator::{
    user_pass_security_policy_id, AuthManager, Password, UserToken,
};
use opcua::server::ServerEndpoint;
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};
use tracing::info;

use crate::users::{Role, Users};

/// Our user tokens: `user:<name>`, so no user name can pass for the
/// stack's anonymous token.
const USER_PREFIX: &str = "user:";

pub struct Auth {
    pub users: Arc<Users>,
    pub anonymous: bool,
}

/// Whether the session's user may write (role `write`).
pub fn may_write(users: &Users, token: &UserToken) -> bool {
    token
        .0
        .strip_prefix(USER_PREFIX)
        .and_then(|name| users.role(name))
        == Some(Role::Write)
}

#[async_trait]
impl AuthManager for Auth {
    async fn authenticate_anonymous_token(&self, _endpoint: &ServerEndpoint) -> Result<(), Error> {
        if self.anonymous {
            Ok(())
        } else {
            Err(Error::new(
                StatusCode::BadIdentityTokenRejected,
                "anonymous sessions are refused off loopback (OPCUA_ANONYMOUS)",
            ))
        }
    }

    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        let users = self.users.clone();
        let name = username.to_string();
        let password = password.get().as_bytes().to_vec();
        // PBKDF2 is slow on purpose: off the runtime's threads.
        let role = tokio::task::spawn_blocking(move || users.check(&name, &password))
            .await
            .ok()
            .flatten();
        match role {
            Some(role) => {
                info!("OPC UA: user {username} ({role:?}) signed in");
                Ok(UserToken(format!("{USER_PREFIX}{username}")))
            }
            None => {
                info!("OPC UA: sign-in of {username:?} refused");
                Err(Error::new(
                    StatusCode::BadUserAccessDenied,
                    "unknown user or wrong password",
                ))
            }
        }
    }

    fn effective_user_access_level(
        &self,
        token: &UserToken,
        user_access_level: AccessLevel,
        _node_id: &NodeId,
    ) -> AccessLevel {
        if may_write(&self.users, token) {
            user_access_level
        } else {
            user_access_level - AccessLevel::CURRENT_WRITE
        }
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        let mut policies = Vec::new();
        if self.anonymous {
            policies.push(UserTokenPolicy {
                policy_id: UAString::from("anonymous"),
                token_type: UserTokenType::Anonymous,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        if !self.users.is_empty() {
            // On an endpoint without security the password is encrypted
            // with Basic256Sha256 all the same (`password_security_policy`).
            let plain = endpoint.security_policy() == SecurityPolicy::None;
            policies.push(UserTokenPolicy {
                policy_id: user_pass_security_policy_id(endpoint),
                token_type: UserTokenType::UserName,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: if plain {
                    UAString::from(SecurityPolicy::Basic256Sha256.to_uri())
                } else {
                    UAString::null()
                },
            });
        }
        policies
    }
}
