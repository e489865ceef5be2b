//! The transport's floor for `dhg-serve`: a bare Zenoh peer with the server's key space and quality of service
//! that answers each pose with a force-layout put straight from its subscriber callback, with no
//! engine, no tick and no comm thread. The load tool (`examples/load.rs`) runs against it as
//! against `dhg-serve`, so `tests/benchmarks/bench_server.py --against-echo` can set what the
//! server costs beside what Zenoh itself costs, alternating the two in one run.
//!
//! ```text
//! cargo run --release -p bone_sim --example echo -- --listen tcp/127.0.0.1:7447
//! cargo run --release -p bone_sim --example load -- --connect tcp/127.0.0.1:7447 --clients 4
//! ```
//!
//! What it answers, as `dhg-serve` does (`docs/protocol.md`): `<p>/session/<id>/control` (any op:
//! the session info's `entry_m` and `target_m` of a fixed path, declaring the session's force
//! publisher on first sight), `<p>/session/*/pose` (a force message echoing the pose's sequence
//! number and client time, on a publisher with the server's congestion control, priority and
//! express flag) and `<p>/server/health` (an empty report: the load tool then prints null for
//! the server-side figures). Poses that do not decode are counted and dropped.
//!
//! `--mode router` runs it in Zenoh's router mode, as `dhg-serve`'s engine runs (default `peer`).
//!
//! `--work-us US` makes each pose's callback spin that long before it answers: a stand-in for the
//! tick's work, so that `bench_threads.py --echo-work-us` parts what the tick costs by itself from
//! what the engine costs around it.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use bone_sim::protocol::{self, decode_pose, encode_force, ForceMsg};
use nalgebra::Vector3;
use zenoh::bytes::Encoding;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::Wait;

/// A fixed planned path (m), along z: the echo has no bone.
const ENTRY_M: [f64; 3] = [0.0, 0.0, 0.0];
const TARGET_M: [f64; 3] = [0.0, 0.0, 0.08];

type Publishers = Arc<RwLock<HashMap<String, zenoh::pubsub::Publisher<'static>>>>;

fn main() {
    let mut listen = "tcp/127.0.0.1:7447".to_string();
    let mut prefix = "dhg".to_string();
    let mut transport = "{}".to_string();
    let mut work_us = 0.0_f64;
    let mut mode = "peer".to_string();
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        match (flag.as_str(), it.next()) {
            ("--listen", Some(v)) => listen = v,
            ("--prefix", Some(v)) => prefix = v,
            ("--transport", Some(v)) => transport = v,
            ("--mode", Some(v)) if v == "peer" || v == "router" => mode = v,
            ("--work-us", Some(v)) if v.parse::<f64>().is_ok_and(|w| (0.0..=1000.0).contains(&w)) => {
                work_us = v.parse().unwrap_or(0.0);
            }
            _ => {
                eprintln!(
                    "usage: echo [--listen ENDPOINT] [--prefix P] [--transport JSON5 (zenoh's transport section)] \
                     [--mode peer|router (default peer)] [--work-us US (0-1000: spin this long in each pose's callback, a stand-in for a tick)]"
                );
                std::process::exit(2);
            }
        }
    }
    if let Err(e) = bone_sim::transport::check_zenoh_runtime() {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
    if let Err(e) = run(&listen, &prefix, &transport, &mode, Duration::from_secs_f64(work_us * 1e-6)) {
        eprintln!("error: {e}");
        std::process::exit(5);
    }
}

fn run(listen: &str, prefix: &str, transport: &str, mode: &str, work: Duration) -> Result<(), String> {
    let conf = format!(
        r#"{{ mode: "{mode}", listen: {{ endpoints: ["{listen}"] }}, scouting: {{ multicast: {{ enabled: false }} }}, transport: {transport} }}"#
    );
    let zc = zenoh::Config::from_json5(&conf).map_err(|e| e.to_string())?;
    let session = zenoh::open(zc).wait().map_err(|e| format!("cannot listen on {listen}: {e}"))?;
    let publishers: Publishers = Arc::default();
    let refused = Arc::new(AtomicU64::new(0));

    let session_prefix = format!("{prefix}/session/");
    let (pubs, s2, p2) = (publishers.clone(), session.clone(), session_prefix.clone());
    let _control = session
        .declare_queryable(format!("{prefix}/session/*/control"))
        .callback(move |query| {
            let key = query.key_expr().as_str().to_string();
            let id = key.strip_prefix(&p2).and_then(|k| k.strip_suffix("/control")).unwrap_or("").to_string();
            let mut map = pubs.write().unwrap_or_else(std::sync::PoisonError::into_inner);
            if !map.contains_key(&id) {
                if let Ok(p) = s2
                    .declare_publisher(format!("{p2}{id}/force"))
                    .encoding(
                        Encoding::APPLICATION_OCTET_STREAM.with_schema(format!("dhg.force.v{}", protocol::VERSION)),
                    )
                    .congestion_control(CongestionControl::Drop)
                    .priority(Priority::RealTime)
                    .express(true)
                    .wait()
                {
                    map.insert(id.clone(), p);
                }
            }
            drop(map);
            let info = serde_json::json!({ "session": id, "entry_m": ENTRY_M, "target_m": TARGET_M });
            let _ = query.reply(key, info.to_string()).wait();
        })
        .wait()
        .map_err(|e| e.to_string())?;

    let (pubs, p3, bad) = (publishers.clone(), session_prefix.clone(), refused.clone());
    let _poses = session
        .declare_subscriber(format!("{prefix}/session/*/pose"))
        .callback(move |sample| {
            let Some(id) = sample.key_expr().as_str().strip_prefix(&p3).and_then(|k| k.strip_suffix("/pose")) else {
                return;
            };
            let Ok(pose) = decode_pose(&sample.payload().to_bytes()) else {
                bad.fetch_add(1, Ordering::Relaxed);
                return;
            };
            if !work.is_zero() {
                // A stand-in for the engine's tick (`--work-us`): the same thread busy that long.
                let t0 = Instant::now();
                while t0.elapsed() < work {
                    std::hint::spin_loop();
                }
            }
            let map = pubs.read().unwrap_or_else(std::sync::PoisonError::into_inner);
            if let Some(publisher) = map.get(id) {
                let p = pose.pose.position_m;
                let msg = ForceMsg {
                    pose_seq: pose.seq,
                    pose_client_time_ns: pose.client_time_ns,
                    tick: u64::from(pose.seq),
                    tip_m: Vector3::new(p.x, p.y, p.z),
                    ..ForceMsg::default()
                };
                let _ = publisher.put(encode_force(&msg).to_vec()).wait();
            }
        })
        .wait()
        .map_err(|e| e.to_string())?;

    let bad = refused.clone();
    let _health = session
        .declare_queryable(format!("{prefix}/server/health"))
        .callback(move |query| {
            let report = serde_json::json!({ "echo": true, "refused_poses": bad.load(Ordering::Relaxed) });
            let _ = query.reply(query.key_expr().clone(), report.to_string()).wait();
        })
        .wait()
        .map_err(|e| e.to_string())?;

    eprintln!("echo listening on {listen} (prefix {prefix}); Ctrl-C or SIGTERM stops it");
    loop {
        std::thread::park();
    }
}
