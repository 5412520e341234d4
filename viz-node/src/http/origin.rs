//! Which `Host` and `Origin` the viewer answers to, checked on every request, token or not.
//!
//! - **Host** (DNS rebinding: a name the attacker controls made to resolve to this machine,
//!   so that a page of theirs reads the API as same-origin): the request's `Host` must be an
//!   IP address (v4, or v6 in brackets), `localhost`, or one of the names configured in
//!   `http_hosts`. A rebinding attack needs a name of its own, which is none of these.
//! - **Origin** (another site's page opening the live socket, which the same-origin policy
//!   does not guard, or sending requests): where a browser sends `Origin`, its host and port
//!   must be the request's own `Host`, or a configured name. Requests without `Origin` (curl,
//!   scripts, the page's own navigation) pass.

use std::net::IpAddr;

/// The names the viewer answers to besides IP addresses and `localhost`.
#[derive(Clone, Debug, Default)]
pub struct Allowed {
    names: Vec<String>,
}

impl Allowed {
    /// Names as `http_hosts` lists them (`viz.example.org`, with or without a port); compared
    /// without case.
    pub fn new(names: &[String]) -> Self {
        Self {
            names: names
                .iter()
                .map(|n| host_of(n).to_ascii_lowercase())
                .collect(),
        }
    }

    /// Whether a request with `Host: host` is answered.
    pub fn host(&self, host: &str) -> bool {
        let name = host_of(host);
        is_ip(name)
            || name.eq_ignore_ascii_case("localhost")
            || self.names.iter().any(|n| n.eq_ignore_ascii_case(name))
    }

    /// Whether a request from `origin` (`scheme://host[:port]`) to `host` (its `Host`) is
    /// answered: the same host and port, or a configured name.
    pub fn origin(&self, origin: &str, host: &str) -> bool {
        let Some((_, authority)) = origin.split_once("://") else {
            return false; // "null" (a sandboxed or file page) or garbage
        };
        authority.eq_ignore_ascii_case(host)
            || self
                .names
                .iter()
                .any(|n| n.eq_ignore_ascii_case(host_of(authority)))
    }
}

/// `host` of `host[:port]` (`[v6]` keeps its brackets).
fn host_of(authority: &str) -> &str {
    if authority.starts_with('[') {
        return authority
            .find(']')
            .map_or(authority, |end| &authority[..=end]);
    }
    authority.split(':').next().unwrap_or(authority)
}

fn is_ip(name: &str) -> bool {
    let bare = name.trim_start_matches('[').trim_end_matches(']');
    bare.parse::<IpAddr>().is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_are_addresses_localhost_or_configured_names() {
        let a = Allowed::new(&["viz.example.org".into(), "Other.Lab:8443".into()]);
        for ok in [
            "127.0.0.1:8080",
            "10.1.2.3",
            "[::1]:8080",
            "localhost:8080",
            "LOCALHOST",
            "viz.example.org:8080",
            "other.lab",
        ] {
            assert!(a.host(ok), "{ok}");
        }
        for refused in [
            "evil.example:8080",
            "127.0.0.1.evil.example",
            "",
            "viz.example.org.evil",
        ] {
            assert!(!a.host(refused), "{refused}");
        }
        assert!(!Allowed::default().host("viz.example.org"));
    }

    #[test]
    fn origins_are_the_request_s_own_host_or_configured_names() {
        let a = Allowed::new(&["viz.example.org".into()]);
        assert!(a.origin("http://127.0.0.1:8080", "127.0.0.1:8080"));
        assert!(a.origin("https://viz.example.org", "10.0.0.5:443"));
        assert!(
            !a.origin("http://127.0.0.1:9999", "127.0.0.1:8080"),
            "another port"
        );
        assert!(!a.origin("https://evil.example", "127.0.0.1:8080"));
        assert!(!a.origin("null", "127.0.0.1:8080"));
    }
}
