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
    /// Zenoh's `transport` section as JSON5 (for example shared memory on), instead of the default.
    transport: Option<String>,
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
        transport: None,
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
            "--transport" => a.transport = Some(value()?),
            "--short-slices" => a.short_slices = true,
            "--help" | "-h" => {
                return Err(
                    "usage: load [--connect ENDPOINT] [--clients N] [--seconds S] [--prefix P] [--server-pid PID] [--lowlatency | --transport JSON5] [--short-slices]"
                        .into(),
                )
            }
            other => return Err(format!("unknown option {other}")),
        }
    }
    if a.clients == 0 || !a.seconds.is_finite() || a.seconds <= 0.0 {
        return Err("--clients and --seconds must be positive".into());
    }
    if a.lowlatency && a.transport.is_some() {
        return Err("--lowlatency and --transport both set Zenoh's transport section: give one".into());
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
    if let Err(e) = bone_sim::transport::check_zenoh_runtime() {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
    if let Err(e) = run(&args) {
        eprintln!("error: {e}");
        std::process::exit(5);
    }
}

#[allow(clippy::too_many_lines)]
/// What every client's callbacks share with the measuring loop.
struct Shared {
    /// The clock every send and receive time is read from (ns since `base`).
    base: Instant,
    /// 1 while the measured window runs.
    measuring: AtomicU64,
    lat: Mutex<Latencies>,
    /// Forces for the counted poses, and guidance messages received.
    forces: AtomicU64,
    guidance: AtomicU64,
    /// The poses whose forces are counted.
    counted: std::ops::Range<u64>,
    /// Poses sent per client (sequence numbers 1..=total).
    total: u64,
}

impl Shared {
    fn now_ns(&self) -> u64 {
        self.base.elapsed().as_nanos() as u64
    }
    fn measuring(&self) -> bool {
        self.measuring.load(Ordering::Relaxed) == 1
    }
}

const WARMUP_TICKS: u64 = 2000;

fn run(args: &Args) -> Result<(), String> {
    let total = WARMUP_TICKS + (args.seconds * 1000.0) as u64;
    // Forces are counted by the pose they echo: those of the measured poses (seq warmup + 1 ..
    // total), less the last one, whose session goes on ticking at 1 kHz without a newer pose. So
    // forces per pose is the session's tick rate over its client's: 1 when locked.
    let shared = Arc::new(Shared {
        base: Instant::now(),
        measuring: AtomicU64::new(0),
        lat: Mutex::new(Latencies::default()),
        forces: AtomicU64::new(0),
        guidance: AtomicU64::new(0),
        counted: (WARMUP_TICKS + 1)..total,
        total,
    });
    let clients = (0..args.clients).map(|c| connect(args, c, &shared)).collect::<Result<Vec<_>, _>>()?;
    eprintln!("{} clients connected; streaming for 2 s of warm-up plus {} s", clients.len(), args.seconds);
    let client_slices = if args.short_slices {
        usize::from(realtime::short_slice(0)) + realtime::short_slice_named(&ZENOH_IO_THREADS)
    } else {
        0
    };
    let cpu0 = args.server_pid.and_then(cpu_ticks);
    let (window_s, late_sends) = stream(&clients, &shared);
    let cpu1 = args.server_pid.and_then(cpu_ticks);
    let health = query_json(
        &clients[0].session,
        &format!("{}/server/health?window={}", args.prefix, args.seconds.ceil()),
        None,
    )?;
    let clk = 100.0; // USER_HZ on Linux
    let cpu = match (cpu0, cpu1) {
        (Some(a), Some(b)) => json!(((b - a) as f64 / clk) / (window_s + 2.3)),
        _ => Value::Null,
    };
    let mut report = report(&shared, &health, clients.len(), window_s);
    report["client_short_slices"] = json!(client_slices);
    report["server_cpu_cores"] = cpu;
    report["client_late_sends"] = json!(late_sends);
    println!("{report}");
    for c in &clients {
        let _ = query_json(&c.session, &format!("{}/control", c.key), Some(r#"{"op":"close"}"#.into()));
    }
    for c in clients {
        let _ = c.session.close().wait();
    }
    Ok(())
}

/// Client `c`: its own Zenoh session, its session on the server, its pose publisher and its
/// force and guidance subscribers.
fn connect(args: &Args, c: usize, shared: &Arc<Shared>) -> Result<Client, String> {
    let transport = match (&args.transport, args.lowlatency) {
        (Some(t), _) => t.as_str(),
        (None, true) => LOWLATENCY,
        (None, false) => "{}",
    };
    let conf = format!(
        r#"{{ mode: "client", connect: {{ endpoints: ["{}"] }}, scouting: {{ multicast: {{ enabled: false }} }}, transport: {transport} }}"#,
        args.connect
    );
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
    let orientation = UnitQuaternion::rotation_between(&Vector3::z(), &dir).unwrap_or_else(UnitQuaternion::identity);
    let publisher = session
        .declare_publisher(format!("{base_key}/pose"))
        .congestion_control(CongestionControl::Drop)
        .priority(Priority::RealTime)
        .express(true)
        .wait()
        .map_err(|e| e.to_string())?;
    let sent_ns: Arc<Vec<AtomicU64>> = Arc::new((0..=shared.total).map(|_| AtomicU64::new(0)).collect());
    let fsub = on_forces(&session, &base_key, shared.clone(), sent_ns.clone())?;
    let gsub = on_guidance(&session, &base_key, shared.clone())?;
    Ok(Client { session, key: base_key, publisher, sent_ns, entry, dir, orientation, _subs: vec![fsub, gsub] })
}

/// Counts a client's forces and, while measuring, records each pose's latency to its first force
/// (`force`) and to the first force from it or a newer pose (`fresh_force`).
fn on_forces(
    session: &zenoh::Session,
    base_key: &str,
    shared: Arc<Shared>,
    sent: Arc<Vec<AtomicU64>>,
) -> Result<zenoh::pubsub::Subscriber<()>, String> {
    let f_off = echo_offset(&FORCE);
    // A pose's latency is that of the first force echoing it: later ones echo the same pose
    // until a newer one is used, and would count its age.
    let (last_seq, newest) = (AtomicU64::new(u64::MAX), AtomicU64::new(0));
    session
        .declare_subscriber(format!("{base_key}/force"))
        .callback(move |s| {
            let b = s.payload().to_bytes();
            if b.len() < f_off + 8 {
                return;
            }
            let seq = u64::from(u32::from_le_bytes(b[4..8].try_into().unwrap()));
            if shared.counted.contains(&seq) {
                shared.forces.fetch_add(1, Ordering::Relaxed);
            }
            if !shared.measuring() {
                return;
            }
            let echoed = u64::from_le_bytes(b[f_off..f_off + 8].try_into().unwrap());
            let now = shared.now_ns();
            if echoed > 0 && last_seq.swap(seq, Ordering::Relaxed) != seq {
                shared.lat.lock().unwrap().force.push(now.saturating_sub(echoed));
            }
            // This force answers every pose up to `seq` not yet answered.
            let before = newest.fetch_max(seq, Ordering::Relaxed);
            if seq > before && before > 0 {
                let mut l = shared.lat.lock().unwrap();
                for q in (before + 1)..=seq.min(sent.len() as u64 - 1) {
                    let t = sent[q as usize].load(Ordering::Relaxed);
                    if t > 0 && shared.counted.contains(&q) {
                        l.fresh_force.push(now.saturating_sub(t));
                    }
                }
            }
        })
        .wait()
        .map_err(|e| e.to_string())
}

/// Counts a client's guidance messages and records each one's latency from the pose it echoes.
fn on_guidance(
    session: &zenoh::Session,
    base_key: &str,
    shared: Arc<Shared>,
) -> Result<zenoh::pubsub::Subscriber<()>, String> {
    let g_off = echo_offset(&GUIDANCE);
    let last_echo = AtomicU64::new(u64::MAX);
    session
        .declare_subscriber(format!("{base_key}/guidance"))
        .callback(move |s| {
            let b = s.payload().to_bytes();
            if shared.measuring() && b.len() >= g_off + 8 {
                let echoed = u64::from_le_bytes(b[g_off..g_off + 8].try_into().unwrap());
                shared.guidance.fetch_add(1, Ordering::Relaxed);
                if echoed > 0 && last_echo.swap(echoed, Ordering::Relaxed) != echoed {
                    shared.lat.lock().unwrap().guidance.push(shared.now_ns().saturating_sub(echoed));
                }
            }
        })
        .wait()
        .map_err(|e| e.to_string())
}

/// Streams every client's poses at 1 kHz on absolute deadlines: 2 s of warm-up, then the
/// measured window. Returns the window's length (s) and the sends more than 1 ms late.
fn stream(clients: &[Client], shared: &Shared) -> (f64, u64) {
    let mut measured_from = Instant::now();
    let start = Instant::now();
    let mut late_sends = 0u64;
    for k in 0..shared.total {
        if k == WARMUP_TICKS {
            shared.measuring.store(1, Ordering::SeqCst);
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
            let msg = PoseMsg { seq: (k + 1) as u32, client_time_ns: shared.now_ns(), pose };
            c.sent_ns[(k + 1) as usize].store(msg.client_time_ns, Ordering::Relaxed);
            let _ = c.publisher.put(encode_pose(&msg).to_vec()).wait();
        }
    }
    std::thread::sleep(Duration::from_millis(300));
    shared.measuring.store(0, Ordering::SeqCst);
    (measured_from.elapsed().as_secs_f64() - 0.3, late_sends)
}

/// The run's figures: counts, latency quantiles (ms) and the server's own health figures.
fn report(shared: &Shared, health: &Value, clients: usize, window_s: f64) -> Value {
    let mut l = shared.lat.lock().unwrap();
    let expected = (shared.counted.end - shared.counted.start) * clients as u64;
    let received = shared.forces.load(Ordering::Relaxed);
    let ms = |k: &str| health[k].as_f64().unwrap_or(f64::NAN) * 1e3;
    json!({
        "clients": clients,
        "seconds": window_s,
        "forces_received": received,
        "forces_expected": expected,
        "forces_per_pose": received as f64 / expected as f64,
        // Measured poses that got a force of their own (the latencies are theirs): a pose
        // superseded before its tick has none, so more own ticks can raise the quantiles.
        "poses_with_own_force": l.force.len(),
        "guidance_received": shared.guidance.load(Ordering::Relaxed),
        "pose_to_force_ms": { "p50": quantile_ms(&mut l.force, 0.5), "p99": quantile_ms(&mut l.force, 0.99), "p999": quantile_ms(&mut l.force, 0.999) },
        // Every measured pose, superseded ones included: to the first force from it or a newer pose.
        "pose_to_fresh_force_ms": { "p50": quantile_ms(&mut l.fresh_force, 0.5), "p99": quantile_ms(&mut l.fresh_force, 0.99), "p999": quantile_ms(&mut l.fresh_force, 0.999) },
        "pose_to_guidance_ms": { "p50": quantile_ms(&mut l.guidance, 0.5), "p99": quantile_ms(&mut l.guidance, 0.99) },
        "tick_lateness_ms": { "p99": ms("tick_lateness_p99_s"), "p999": ms("tick_lateness_p999_s") },
        // The server's part of pose → force (arrival in its subscriber to the force's put).
        "server_pose_to_put_ms": { "p50": ms("pose_to_put_p50_s"), "p99": ms("pose_to_put_p99_s"), "p999": ms("pose_to_put_p999_s") },
        // Its first part: arrival to the tick that used the pose (the rest is the comm thread's put).
        "server_pose_to_tick_ms": { "p50": ms("pose_to_tick_p50_s"), "p99": ms("pose_to_tick_p99_s"), "p999": ms("pose_to_tick_p999_s") },
        "tick_busy_p99_us": health["tick_busy_p99_s"].as_f64().unwrap_or(f64::NAN) * 1e6,
        "missed_ticks": health["missed_ticks"],
        // Ticks per session per second of the server's window: above 1000 means sessions ran
        // fast (simulated time ahead of the wall clock), below it that ticks were missed.
        "session_tick_hz": health["ticks"].as_f64().unwrap_or(f64::NAN)
            / health["window_s"].as_f64().unwrap_or(f64::NAN)
            / clients as f64,
        "tick_realtime": health["tick_realtime"],
        "tick_wait": health["tick_wait"],
        "short_slices": health["short_slices"],
    })
}
