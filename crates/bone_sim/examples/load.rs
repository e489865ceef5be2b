//! Load tool for `dhg-serve`: N simulated trainees, each its own Zenoh session, each streaming
//! stylus poses at 1 kHz and drilling into the bone along its planned path. Measures pose → force
//! and pose → guidance latency on this process's clock (the server echoes it), counts messages,
//! and reads the server's health (tick lateness, missed ticks) and, with `--server-pid`, its CPU.
//!
//! ```text
//! dhg-serve --listen tcp/127.0.0.1:7447 --max-sessions 64 &
//! cargo run --release -p bone_sim --example load -- --clients 16 --seconds 60 --server-pid $!
//! ```
//!
//! Prints one JSON object (seconds, counts, quantiles in ms) on stdout.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bone_sim::engine::realtime;
use bone_sim::protocol::{encode_pose, PoseMsg, FORCE, GUIDANCE};
use bone_sim::transport::ZENOH_IO_THREADS;
use bone_sim::Pose;
use nalgebra::{Point3, UnitQuaternion, Vector3};
use serde_json::{json, Value};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::Wait;

/// The `transport` section that turns on Zenoh's low-latency transport (priorities off).
const LOWLATENCY: &str = "{ unicast: { lowlatency: true, qos: { enabled: false } } }";

struct Args {
    connect: String,
    clients: usize,
    seconds: f64,
    prefix: String,
    server_pid: Option<u32>,
    /// Zenoh's low-latency transport (priorities off): each put is written by the calling thread.
    lowlatency: bool,
    /// Give this tool's sending thread and Zenoh's I/O threads the 0.1 ms slice, as the server does.
    short_slices: bool,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        connect: "tcp/127.0.0.1:7447".into(),
        clients: 1,
        seconds: 10.0,
        prefix: "dhg".into(),
        server_pid: None,
        lowlatency: false,
        short_slices: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or_else(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--connect" => a.connect = value()?,
            "--clients" => a.clients = value()?.parse().map_err(|e| format!("--clients: {e}"))?,
            "--seconds" => a.seconds = value()?.parse().map_err(|e| format!("--seconds: {e}"))?,
            "--prefix" => a.prefix = value()?,
            "--server-pid" => a.server_pid = Some(value()?.parse().map_err(|e| format!("--server-pid: {e}"))?),
            "--lowlatency" => a.lowlatency = true,
            "--short-slices" => a.short_slices = true,
            "--help" | "-h" => {
                return Err(
                    "usage: load [--connect ENDPOINT] [--clients N] [--seconds S] [--prefix P] [--server-pid PID] [--lowlatency] [--short-slices]"
                        .into(),
                )
            }
            other => return Err(format!("unknown option {other}")),
        }
    }
    if a.clients == 0 || !a.seconds.is_finite() || a.seconds <= 0.0 {
        return Err("--clients and --seconds must be positive".into());
    }
    Ok(a)
}

/// Offset of the echoed client time in a layout.
fn echo_offset(layout: &bone_sim::protocol::Layout) -> usize {
    layout.fields.iter().find(|f| f.name == "pose_client_time_ns").map(|f| f.offset).expect("layout has an echo")
}

/// Latencies (ns) gathered while measuring.
#[derive(Default)]
struct Latencies {
    /// From each pose's send to the first force computed from it.
    force: Vec<u64>,
    /// From each measured pose's send to the first force computed from it or a newer pose (a
    /// superseded pose counts too, with the wait its client saw).
    fresh_force: Vec<u64>,
    /// From the pose a guidance message echoes to that message.
    guidance: Vec<u64>,
}

struct Client {
    session: zenoh::Session,
    key: String,
    publisher: zenoh::pubsub::Publisher<'static>,
    /// Send time (ns, `now_ns`) of each pose, by sequence number.
    sent_ns: Arc<Vec<AtomicU64>>,
    entry: Point3<f64>,
    dir: Vector3<f64>,
    orientation: UnitQuaternion<f64>,
    _subs: Vec<zenoh::pubsub::Subscriber<()>>,
}

fn quantile_ms(v: &mut [u64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    v[i] as f64 * 1e-6
}

fn cpu_ticks(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let after = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = after.split_whitespace().collect();
    Some(f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?)
}

fn query_json(session: &zenoh::Session, key: &str, body: Option<String>) -> Result<Value, String> {
    let mut get = session.get(key).timeout(Duration::from_secs(3));
    if let Some(b) = body {
        get = get.payload(b);
    }
    let replies = get.wait().map_err(|e| format!("{key}: {e}"))?;
    if let Ok(reply) = replies.recv() {
        match reply.result() {
            Ok(s) => return serde_json::from_slice(&s.payload().to_bytes()).map_err(|e| format!("{key}: {e}")),
            Err(e) => return Err(format!("{key}: {}", String::from_utf8_lossy(&e.payload().to_bytes()))),
        }
    }
    Err(format!("{key}: no reply (is dhg-serve running at that endpoint?)"))
}

fn main() {
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(2);
        }
    };
    if let Err(e) = run(&args) {
        eprintln!("error: {e}");
        std::process::exit(5);
    }
}

#[allow(clippy::too_many_lines)]
fn run(args: &Args) -> Result<(), String> {
    let base = Instant::now();
    let now_ns = move || base.elapsed().as_nanos() as u64;
    let transport = if args.lowlatency { LOWLATENCY } else { "{}" };
    let conf = format!(
        r#"{{ mode: "client", connect: {{ endpoints: ["{}"] }}, scouting: {{ multicast: {{ enabled: false }} }}, transport: {transport} }}"#,
        args.connect
    );
    let measuring = Arc::new(AtomicU64::new(0)); // 1 while the measured window runs
    let lat = Arc::new(Mutex::new(Latencies::default()));
    let (f_off, g_off) = (echo_offset(&FORCE), echo_offset(&GUIDANCE));
    let forces = Arc::new(AtomicU64::new(0));
    let guidance = Arc::new(AtomicU64::new(0));
    let warmup_ticks = 2000u64;
    let total = warmup_ticks + (args.seconds * 1000.0) as u64;
    // Forces are counted by the pose they echo: those of the measured poses (seq warmup + 1 ..
    // total), less the last one, whose session goes on ticking at 1 kHz without a newer pose. So
    // forces per pose is the session's tick rate over its client's: 1 when locked.
    let counted_seqs = (warmup_ticks + 1)..total;
    let mut clients = Vec::with_capacity(args.clients);
    for c in 0..args.clients {
        let zc = zenoh::Config::from_json5(&conf).map_err(|e| e.to_string())?;
        let session = zenoh::open(zc).wait().map_err(|e| format!("cannot connect to {}: {e}", args.connect))?;
        let id = format!("load-{}-{c}", std::process::id());
        let base_key = format!("{}/session/{id}", args.prefix);
        let info = query_json(&session, &format!("{base_key}/control"), Some(r#"{"op":"create"}"#.into()))?;
        let p = |k: &str| -> Result<Point3<f64>, String> {
            let v: Vec<f64> = serde_json::from_value(info[k].clone()).map_err(|e| format!("{k}: {e}"))?;
            Ok(Point3::new(v[0], v[1], v[2]))
        };
        let (entry, target) = (p("entry_m")?, p("target_m")?);
        let dir = (target - entry).normalize();
        let orientation =
            UnitQuaternion::rotation_between(&Vector3::z(), &dir).unwrap_or_else(UnitQuaternion::identity);
        let publisher = session
            .declare_publisher(format!("{base_key}/pose"))
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::RealTime)
            .express(true)
            .wait()
            .map_err(|e| e.to_string())?;
        // A pose's latency is that of the first force (guidance) echoing it: later ones echo the
        // same pose until a newer one is used, and would count its age.
        let last_seq = AtomicU64::new(u64::MAX);
        let last_echo = AtomicU64::new(u64::MAX);
        let (l1, m1, n1) = (lat.clone(), measuring.clone(), forces.clone());
        let counted = counted_seqs.clone();
        let sent_ns: Arc<Vec<AtomicU64>> = Arc::new((0..=total).map(|_| AtomicU64::new(0)).collect());
        let (sent, newest) = (sent_ns.clone(), AtomicU64::new(0));
        let fsub = session
            .declare_subscriber(format!("{base_key}/force"))
            .callback(move |s| {
                let b = s.payload().to_bytes();
                if b.len() < f_off + 8 {
                    return;
                }
                let seq = u64::from(u32::from_le_bytes(b[4..8].try_into().unwrap()));
                if counted.contains(&seq) {
                    n1.fetch_add(1, Ordering::Relaxed);
                }
                if m1.load(Ordering::Relaxed) == 1 {
                    let echoed = u64::from_le_bytes(b[f_off..f_off + 8].try_into().unwrap());
                    let now = now_ns();
                    if echoed > 0 && last_seq.swap(seq, Ordering::Relaxed) != seq {
                        l1.lock().unwrap().force.push(now.saturating_sub(echoed));
                    }
                    // This force answers every pose up to `seq` not yet answered.
                    let before = newest.fetch_max(seq, Ordering::Relaxed);
                    if seq > before && before > 0 {
                        let mut l = l1.lock().unwrap();
                        for q in (before + 1)..=seq.min(sent.len() as u64 - 1) {
                            let t = sent[q as usize].load(Ordering::Relaxed);
                            if t > 0 && counted.contains(&q) {
                                l.fresh_force.push(now.saturating_sub(t));
                            }
                        }
                    }
                }
            })
            .wait()
            .map_err(|e| e.to_string())?;
        let (l2, m2, n2) = (lat.clone(), measuring.clone(), guidance.clone());
        let gsub = session
            .declare_subscriber(format!("{base_key}/guidance"))
            .callback(move |s| {
                let b = s.payload().to_bytes();
                if m2.load(Ordering::Relaxed) == 1 && b.len() >= g_off + 8 {
                    let echoed = u64::from_le_bytes(b[g_off..g_off + 8].try_into().unwrap());
                    n2.fetch_add(1, Ordering::Relaxed);
                    if echoed > 0 && last_echo.swap(echoed, Ordering::Relaxed) != echoed {
                        l2.lock().unwrap().guidance.push(now_ns().saturating_sub(echoed));
                    }
                }
            })
            .wait()
            .map_err(|e| e.to_string())?;
        clients.push(Client {
            session,
            key: base_key,
            publisher,
            sent_ns,
            entry,
            dir,
            orientation,
            _subs: vec![fsub, gsub],
        });
    }
    eprintln!("{} clients connected; streaming for 2 s of warm-up plus {} s", clients.len(), args.seconds);
    let client_slices = if args.short_slices {
        usize::from(realtime::short_slice(0)) + realtime::short_slice_named(&ZENOH_IO_THREADS)
    } else {
        0
    };
    let cpu0 = args.server_pid.and_then(cpu_ticks);
    let mut measured_from = Instant::now();
    let start = Instant::now();
    let mut late_sends = 0u64;
    for k in 0..total {
        if k == warmup_ticks {
            measuring.store(1, Ordering::SeqCst);
            measured_from = Instant::now();
        }
        let deadline = start + Duration::from_millis(k);
        let now = Instant::now();
        if now < deadline {
            std::thread::sleep(deadline - now);
        } else if now - deadline > Duration::from_millis(1) {
            late_sends += 1;
        }
        // Each trainee feeds from 2 mm short of A at 2 mm/s (into the bone after a second).
        let s = -2e-3 + 2e-3 * (k as f64 * 1e-3);
        for (i, c) in clients.iter().enumerate() {
            let position = c.entry + c.dir * (s - i as f64 * 1e-5);
            let pose = Pose { position_m: position, orientation: c.orientation, drill_on: true, spindle_rpm: 1250.0 };
            let msg = PoseMsg { seq: (k + 1) as u32, client_time_ns: now_ns(), pose };
            c.sent_ns[(k + 1) as usize].store(msg.client_time_ns, Ordering::Relaxed);
            let _ = c.publisher.put(encode_pose(&msg).to_vec()).wait();
        }
    }
    std::thread::sleep(Duration::from_millis(300));
    measuring.store(0, Ordering::SeqCst);
    let window_s = measured_from.elapsed().as_secs_f64() - 0.3;
    let cpu1 = args.server_pid.and_then(cpu_ticks);
    let health = query_json(
        &clients[0].session,
        &format!("{}/server/health?window={}", args.prefix, args.seconds.ceil()),
        None,
    )?;
    let mut l = lat.lock().unwrap();
    let clk = 100.0; // USER_HZ on Linux
    let cpu = match (cpu0, cpu1) {
        (Some(a), Some(b)) => json!(((b - a) as f64 / clk) / (window_s + 2.3)),
        _ => Value::Null,
    };
    let expected = (counted_seqs.end - counted_seqs.start) * clients.len() as u64;
    let received = forces.load(Ordering::Relaxed);
    let report = json!({
        "clients": clients.len(),
        "seconds": window_s,
        "forces_received": received,
        "forces_expected": expected,
        "forces_per_pose": received as f64 / expected as f64,
        // Measured poses that got a force of their own (the latencies are theirs): a pose
        // superseded before its tick has none, so more own ticks can raise the quantiles.
        "poses_with_own_force": l.force.len(),
        "guidance_received": guidance.load(Ordering::Relaxed),
        "pose_to_force_ms": { "p50": quantile_ms(&mut l.force, 0.5), "p99": quantile_ms(&mut l.force, 0.99), "p999": quantile_ms(&mut l.force, 0.999) },
        // Every measured pose, superseded ones included: to the first force from it or a newer pose.
        "pose_to_fresh_force_ms": { "p50": quantile_ms(&mut l.fresh_force, 0.5), "p99": quantile_ms(&mut l.fresh_force, 0.99), "p999": quantile_ms(&mut l.fresh_force, 0.999) },
        "pose_to_guidance_ms": { "p50": quantile_ms(&mut l.guidance, 0.5), "p99": quantile_ms(&mut l.guidance, 0.99) },
        "tick_lateness_ms": { "p99": health["tick_lateness_p99_s"].as_f64().unwrap_or(f64::NAN) * 1e3, "p999": health["tick_lateness_p999_s"].as_f64().unwrap_or(f64::NAN) * 1e3 },
        // The server's part of pose → force (arrival in its subscriber to the force's put).
        "server_pose_to_put_ms": {
            "p50": health["pose_to_put_p50_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
            "p99": health["pose_to_put_p99_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
            "p999": health["pose_to_put_p999_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
        },
        // Its first part: arrival to the tick that used the pose (the rest is the comm thread's put).
        "server_pose_to_tick_ms": {
            "p50": health["pose_to_tick_p50_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
            "p99": health["pose_to_tick_p99_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
            "p999": health["pose_to_tick_p999_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
        },
        "tick_busy_p99_us": health["tick_busy_p99_s"].as_f64().unwrap_or(f64::NAN) * 1e6,
        "missed_ticks": health["missed_ticks"],
        // Ticks per session per second of the server's window: above 1000 means sessions ran
        // fast (simulated time ahead of the wall clock), below it that ticks were missed.
        "session_tick_hz": health["ticks"].as_f64().unwrap_or(f64::NAN)
            / health["window_s"].as_f64().unwrap_or(f64::NAN)
            / clients.len() as f64,
        "tick_realtime": health["tick_realtime"],
        "tick_wait": health["tick_wait"],
        "short_slices": health["short_slices"],
        "client_short_slices": client_slices,
        "server_cpu_cores": cpu,
        "client_late_sends": late_sends,
    });
    println!("{report}");
    drop(l);
    for c in &clients {
        let _ = query_json(&c.session, &format!("{}/control", c.key), Some(r#"{"op":"close"}"#.into()));
    }
    for c in clients {
        let _ = c.session.close().wait();
    }
    Ok(())
}
