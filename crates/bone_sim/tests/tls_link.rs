//! Zenoh's TLS link under full-duplex load: the secure lab mode's transport (docs/deployment.md).
//!
//! Upstream's link (zenoh-link-tls 1.10.2) read and wrote one rustls connection from two tasks
//! at once through an `UnsafeCell` (eclipse-zenoh/zenoh#2557). The data race corrupted rustls's
//! state: writes failed while a read held the state, links dropped, and `dhg-serve` aborted in
//! rustls's `Error::clone` ("memory allocation of 140406507659648 bytes failed"). The workspace
//! builds a patched copy (`vendor/zenoh-link-tls`, each half of the stream behind its own lock).
//!
//! Two sessions in this process, one listening on TLS and one connected to it, each publishing
//! to the other as fast as the link takes it: with the upstream link this broke the link or the
//! process within seconds; with the patched one every message arrives, in order, on one link.
//! The certificates are made in the test (rcgen), so it needs no `openssl` and never skips.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::qos::CongestionControl;
use zenoh::Wait;

/// How long each side publishes: long enough that the upstream link failed every time here.
const STREAM_FOR: Duration = Duration::from_secs(4);
/// Payload of each message (bytes): several TLS records' worth, so reads and writes overlap.
const PAYLOAD_BYTES: usize = 24 * 1024;

/// A CA and a server certificate for localhost / 127.0.0.1 (P-256 ECDSA, made with rcgen), in a
/// fresh temporary directory as `ca.pem`, `cert.pem` and `key.pem`.
fn certificates() -> PathBuf {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
    let dir = std::env::temp_dir().join(format!("dhg-tls-link-{}-{nanos}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let ca_key = KeyPair::generate().unwrap();
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params.distinguished_name.push(DnType::CommonName, "test CA");
    let ca_cert = ca_params.self_signed(&ca_key).unwrap();
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(vec!["localhost".to_owned(), "127.0.0.1".to_owned()]).unwrap();
    params.distinguished_name.push(DnType::CommonName, "localhost");
    let cert = params.signed_by(&key, &Issuer::new(ca_params, ca_key)).unwrap();
    std::fs::write(dir.join("ca.pem"), ca_cert.pem()).unwrap();
    std::fs::write(dir.join("cert.pem"), cert.pem()).unwrap();
    std::fs::write(dir.join("key.pem"), key.serialize_pem()).unwrap();
    dir
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn session(dir: &Path, endpoints: &str, listen: bool) -> zenoh::Session {
    let p = |f: &str| dir.join(f).display().to_string();
    let side = if listen { "listen" } else { "connect" };
    let tls = if listen {
        format!(
            r#""root_ca_certificate": "{}", "listen_certificate": "{}", "listen_private_key": "{}""#,
            p("ca.pem"),
            p("cert.pem"),
            p("key.pem")
        )
    } else {
        format!(r#""root_ca_certificate": "{}""#, p("ca.pem"))
    };
    let conf = format!(
        r#"{{"mode": "peer", "{side}": {{"endpoints": ["{endpoints}"]}}, "scouting": {{"multicast": {{"enabled": false}}, "gossip": {{"enabled": false}}}}, "transport": {{"link": {{"tls": {{{tls}}}}}}}}}"#
    );
    zenoh::open(zenoh::Config::from_json5(&conf).unwrap()).wait().unwrap()
}

fn publisher(s: &zenoh::Session, key: &'static str) -> zenoh::pubsub::Publisher<'static> {
    s.declare_publisher(key).congestion_control(CongestionControl::Block).wait().unwrap()
}

/// Publishes numbered payloads until `stop`; returns how many were put.
fn flood(publisher: &zenoh::pubsub::Publisher<'static>, stop: &AtomicBool) -> u64 {
    let mut n = 0u64;
    while !stop.load(Ordering::Relaxed) {
        let mut payload = vec![0u8; PAYLOAD_BYTES];
        payload[..8].copy_from_slice(&n.to_le_bytes());
        publisher.put(payload).wait().unwrap();
        n += 1;
    }
    n
}

/// Counts what arrives on `key`, and how many arrived out of sequence.
fn counter(s: &zenoh::Session, key: &'static str) -> (Arc<AtomicU64>, Arc<AtomicU64>, zenoh::pubsub::Subscriber<()>) {
    let (got, out_of_order) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let (g, o) = (got.clone(), out_of_order.clone());
    let sub = s
        .declare_subscriber(key)
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            let seq = u64::from_le_bytes(bytes[..8].try_into().unwrap());
            if seq != g.fetch_add(1, Ordering::Relaxed) || bytes.len() != PAYLOAD_BYTES {
                o.fetch_add(1, Ordering::Relaxed);
            }
        })
        .wait()
        .unwrap();
    (got, out_of_order, sub)
}

fn wait_for(cond: impl Fn() -> bool, deadline: Duration) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < deadline {
        if cond() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    cond()
}

#[test]
fn a_tls_link_carries_traffic_both_ways_at_once_without_breaking() {
    let dir = certificates();
    let port = free_port();
    let a = session(&dir, &format!("tls/127.0.0.1:{port}"), true);
    let b = session(&dir, &format!("tls/localhost:{port}"), false);
    let (at_a, a_disorder, _sa) = counter(&a, "dhg/test/to-a");
    let (at_b, b_disorder, _sb) = counter(&b, "dhg/test/to-b");
    let (pub_to_b, pub_to_a) = (publisher(&a, "dhg/test/to-b"), publisher(&b, "dhg/test/to-a"));
    // Each side sees the other's subscriber before the flood, so no message is put into the void.
    let matched = |p: &zenoh::pubsub::Publisher<'static>| p.matching_status().wait().is_ok_and(|m| m.matching());
    assert!(
        wait_for(|| matched(&pub_to_b) && matched(&pub_to_a), Duration::from_secs(20)),
        "the two sessions did not connect over TLS"
    );
    let stop = AtomicBool::new(false);
    let (sent_to_b, sent_to_a) = std::thread::scope(|scope| {
        let to_b = scope.spawn(|| flood(&pub_to_b, &stop));
        let to_a = scope.spawn(|| flood(&pub_to_a, &stop));
        std::thread::sleep(STREAM_FOR);
        stop.store(true, Ordering::Relaxed);
        (to_b.join().unwrap(), to_a.join().unwrap())
    });
    let all_arrived = wait_for(
        || at_b.load(Ordering::Relaxed) >= sent_to_b && at_a.load(Ordering::Relaxed) >= sent_to_a,
        Duration::from_secs(30),
    );
    let (got_b, got_a) = (at_b.load(Ordering::Relaxed), at_a.load(Ordering::Relaxed));
    eprintln!("a -> b {got_b} of {sent_to_b}, b -> a {got_a} of {sent_to_a} messages of {PAYLOAD_BYTES} bytes");
    assert!(sent_to_a > 100 && sent_to_b > 100, "too little traffic to test anything: {sent_to_a} / {sent_to_b}");
    assert!(
        all_arrived,
        "a reliable TLS link lost messages: a -> b {got_b} of {sent_to_b}, b -> a {got_a} of {sent_to_a}"
    );
    assert_eq!(
        (a_disorder.load(Ordering::Relaxed), b_disorder.load(Ordering::Relaxed)),
        (0, 0),
        "messages out of order or damaged"
    );
    drop((pub_to_a, pub_to_b));
    let (_, _) = (a.close().wait(), b.close().wait());
    let _ = std::fs::remove_dir_all(dir);
}

/// The version of `name` in the workspace's lock file, and whether it comes from a registry.
fn locked(name: &str) -> Option<(String, bool)> {
    let lock = include_str!("../../../Cargo.lock");
    lock.split("[[package]]").find_map(|entry| {
        let field = |key: &str| {
            entry
                .lines()
                .find_map(|l| l.strip_prefix(&format!("{key} = \"")).map(|v| v.trim_end_matches('"').to_string()))
        };
        (field("name")? == name).then(|| (field("version").unwrap_or_default(), field("source").is_some()))
    })
}

#[test]
fn the_patched_tls_link_is_the_one_built_and_matches_zenoh() {
    let (zenoh, _) = locked("zenoh").expect("zenoh in Cargo.lock");
    let (tls, from_registry) = locked("zenoh-link-tls").expect("zenoh-link-tls in Cargo.lock");
    assert!(!from_registry, "zenoh-link-tls comes from crates.io: the patch (vendor/zenoh-link-tls) no longer applies");
    assert_eq!(
        tls, zenoh,
        "zenoh was upgraded: port the fix of vendor/zenoh-link-tls to the new version, or drop the patch if \
         eclipse-zenoh/zenoh#2557 is fixed there (docs/decisions/0017-patched-tls-link.md)"
    );
}
