//! Bearer tokens with roles (ARCHITECTURE.md "Service contract"): `read` (estimate, list,
//! describe), `write`, `admin`; each role includes the ones before it. Tokens come from
//! `--token-file` (`<role> <token>` lines) or a lone `--token` / `UDAPOSE_TOKEN` (admin).
//! Compared in constant time.

use std::{fs, path::Path};

use anyhow::{Context, Result, bail};
use subtle::ConstantTimeEq;

use crate::error::ApiError;

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Role {
    Read,
    Write,
    Admin,
}

impl Role {
    fn parse(s: &str) -> Option<Role> {
        match s {
            "read" => Some(Role::Read),
            "write" => Some(Role::Write),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Role::Read => "read",
            Role::Write => "write",
            Role::Admin => "admin",
        }
    }
}

/// The configured tokens; empty means no authentication.
#[derive(Clone, Default)]
pub struct Tokens {
    tokens: Vec<(Role, Vec<u8>)>,
}

impl std::fmt::Debug for Tokens {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Tokens({} configured)", self.tokens.len()) // never the secrets
    }
}

impl Tokens {
    pub fn new(admin_token: Option<&str>, token_file: Option<&Path>) -> Result<Self> {
        let mut tokens = Vec::new();
        if let Some(t) = admin_token.filter(|t| !t.is_empty()) {
            tokens.push((Role::Admin, t.as_bytes().to_vec()));
        }
        if let Some(path) = token_file {
            let text = fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            for (i, line) in text.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with('#') {
                    continue;
                }
                let mut parts = line.split_whitespace();
                let (Some(role), Some(token), None) = (parts.next(), parts.next(), parts.next()) else {
                    bail!("{}:{}: expected `<role> <token>`", path.display(), i + 1);
                };
                let Some(role) = Role::parse(role) else {
                    bail!("{}:{}: unknown role {role:?} (read, write or admin)", path.display(), i + 1);
                };
                tokens.push((role, token.as_bytes().to_vec()));
            }
        }
        Ok(Tokens { tokens })
    }

    pub fn enabled(&self) -> bool {
        !self.tokens.is_empty()
    }

    /// Checks an `Authorization` header value for `needed`.
    pub fn check(&self, authorization: Option<&str>, needed: Role) -> Result<(), ApiError> {
        if !self.enabled() {
            return Ok(());
        }
        let Some(presented) = authorization.and_then(bearer) else {
            return Err(ApiError::Unauthenticated("missing bearer token (Authorization: Bearer <token>)".into()));
        };
        // Every token is compared, so the time does not tell which one matched.
        let mut role = None;
        for (r, t) in &self.tokens {
            if bool::from(t.as_slice().ct_eq(presented.as_bytes())) {
                role = role.max(Some(*r));
            }
        }
        match role {
            None => Err(ApiError::Unauthenticated("invalid bearer token".into())),
            Some(r) if r < needed => {
                Err(ApiError::PermissionDenied(format!("the token's role {} lacks {}", r.name(), needed.name())))
            }
            Some(_) => Ok(()),
        }
    }
}

/// The token of an `Authorization: Bearer <token>` value; the scheme is case-insensitive
/// (RFC 7235 §2.1), so `bearer` and `BEARER` are accepted too.
fn bearer(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim().split_once(char::is_whitespace)?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

/// The `WWW-Authenticate` challenge every 401 answer carries (RFC 7235 §4.1).
pub const CHALLENGE: &str = "Bearer realm=\"udapose\"";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scheme_is_case_insensitive() {
        assert_eq!(bearer("Bearer abc"), Some("abc"));
        assert_eq!(bearer("bearer abc"), Some("abc"));
        assert_eq!(bearer("BEARER   abc "), Some("abc"));
        assert_eq!(bearer("Basic abc"), None);
        assert_eq!(bearer("Bearer"), None);
        assert_eq!(bearer("Bearerabc"), None);
    }

    #[test]
    fn roles_include_the_lower_ones() {
        let dir = std::env::temp_dir().join(format!("udapose-tokens-{}", std::process::id()));
        fs::write(&dir, "# comment\nread r-token\nwrite w-token\n").unwrap();
        let tokens = Tokens::new(Some("a-token"), Some(&dir)).unwrap();
        fs::remove_file(&dir).unwrap();
        assert!(tokens.check(Some("Bearer r-token"), Role::Read).is_ok());
        assert!(matches!(tokens.check(Some("Bearer r-token"), Role::Write), Err(ApiError::PermissionDenied(_))));
        assert!(tokens.check(Some("Bearer w-token"), Role::Write).is_ok());
        assert!(tokens.check(Some("Bearer a-token"), Role::Admin).is_ok());
        assert!(matches!(tokens.check(Some("Bearer nope"), Role::Read), Err(ApiError::Unauthenticated(_))));
        assert!(matches!(tokens.check(None, Role::Read), Err(ApiError::Unauthenticated(_))));
        assert!(matches!(tokens.check(Some("Basic r-token"), Role::Read), Err(ApiError::Unauthenticated(_))));
        assert!(Tokens::default().check(None, Role::Admin).is_ok());
    }
}
