//! The Zenoh key space (`docs/protocol.md`, keys): every key the engine and the Python services
//! declare or ask, built here from a prefix and, where the key is a session's or a worker's, its
//! id. Python builds its keys from the same functions ([`layout`], `dhg.core.protocol`).

use std::collections::BTreeMap;

/// The leaves under a session's key `<prefix>/session/<id>`: what a client puts (`pose`), hears
/// (`force`, `guidance`, `state`, `ticks`, the screens' `view/force` and `view/pose`) and asks
/// (`control`, and read-only `info`, `metrics`, `xray/<view>`, `bone`).
pub const SESSION_LEAVES: [&str; 12] = [
    "pose",
    "force",
    "guidance",
    "state",
    "ticks",
    "control",
    "info",
    "metrics",
    "xray",
    "view/force",
    "view/pose",
    "bone",
];
/// The one leaf under a session's key that clients put on (the rest they query or hear).
pub const CLIENT_PUT_LEAF: &str = "pose";
/// The server's own queryables, under `<prefix>/server/`.
pub const SERVER_LEAVES: [&str; 3] = ["health", "about", "volume"];

/// `<prefix>/session/<id>`: the root of a session's keys (`id` may be `*`).
#[must_use]
pub fn session(prefix: &str, id: &str) -> String {
    format!("{prefix}/session/{id}")
}

/// `<prefix>/session/<id>/<leaf>`.
#[must_use]
pub fn session_leaf(prefix: &str, id: &str, leaf: &str) -> String {
    format!("{}/{leaf}", session(prefix, id))
}

/// `<prefix>/server/<leaf>`.
#[must_use]
pub fn server(prefix: &str, leaf: &str) -> String {
    format!("{prefix}/server/{leaf}")
}

/// `<prefix>/model/predict`: the shared model key every model service answers.
#[must_use]
pub fn shared_predict(prefix: &str) -> String {
    format!("{prefix}/model/predict")
}

/// `<prefix>/model/workers/<id>`: a pool worker's liveliness token (`id` may be `*`).
#[must_use]
pub fn worker(prefix: &str, id: &str) -> String {
    format!("{prefix}/model/workers/{id}")
}

/// `<prefix>/model/workers/<id>/predict`: the key a pool worker answers.
#[must_use]
pub fn worker_predict(prefix: &str, id: &str) -> String {
    format!("{}/predict", worker(prefix, id))
}

/// `(id, leaf)` of `<prefix>/session/<id>/<leaf>[/...]` (the leaf's first chunk), if `key` is one.
#[must_use]
pub fn parse_session<'a>(prefix: &str, key: &'a str) -> Option<(&'a str, &'a str)> {
    let rest = key.strip_prefix(prefix)?.strip_prefix("/session/")?;
    let (id, leaf) = rest.split_once('/')?;
    Some((id, leaf.split('/').next().unwrap_or(leaf)))
}

/// The key space as templates with `{prefix}` and `{id}` in place of the prefix and an id, built
/// by the functions above, for Python to fill in (`dhg.core.protocol`).
#[must_use]
pub fn layout() -> BTreeMap<&'static str, String> {
    let (p, id) = ("{prefix}", "{id}");
    BTreeMap::from([
        ("session", session(p, id)),
        ("server", server(p, "{leaf}")),
        ("shared_predict", shared_predict(p)),
        ("worker", worker(p, id)),
        ("worker_predict", worker_predict(p, id)),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_session_key_parses_back_to_its_id_and_leaf() {
        for leaf in SESSION_LEAVES {
            let key = session_leaf("dhg", "station-1", leaf);
            assert_eq!(parse_session("dhg", &key), Some(("station-1", leaf.split('/').next().unwrap())));
        }
        assert_eq!(parse_session("dhg", "dhg/session/a/xray/top"), Some(("a", "xray")));
        assert_eq!(parse_session("dhg", "dhg/server/health"), None);
        assert_eq!(parse_session("dhg", "other/session/a/pose"), None);
        assert_eq!(parse_session("dhg", "dhg/session/a"), None, "no leaf");
    }

    #[test]
    fn the_layout_fills_in_to_the_keys_the_functions_build() {
        let l = layout();
        let fill = |t: &str| t.replace("{prefix}", "p").replace("{id}", "x");
        assert_eq!(fill(&l["session"]), session("p", "x"));
        assert_eq!(fill(&l["worker_predict"]), worker_predict("p", "x"));
        assert_eq!(fill(&l["server"]).replace("{leaf}", "about"), server("p", "about"));
        assert!(CLIENT_PUT_LEAF == SESSION_LEAVES[0]);
    }
}
