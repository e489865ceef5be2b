//! The real-time promise: a tick never allocates, on the tick thread or on the thread a pose
//! arrived on. A counting global allocator watches 3000 ticks of 4 sessions drilling through
//! cortex and cancellous bone (their poses found by session id and handed on through the routes,
//! and two of them ticked by their poses, as `dhg-serve` does), with model replies arriving,
//! snapshots taken, a burr swapped and every output drained. Its own test binary, so no other
//! test allocates while it counts.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use bone_sim::engine::handoff::Command;
use bone_sim::engine::{build, EngineConfig};
use bone_sim::guidance::GuidanceMode;
use bone_sim::protocol::PoseMsg;
use bone_sim::transport::routes::{Route, Routes};
use bone_sim::{Layer, PlannedPath, Pose};
use common::{slab, H};
use nalgebra::{Point3, UnitQuaternion};

struct Counting;

static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator; only counts.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn ticks_do_not_allocate() {
    const NXY: usize = 24;
    let centre = 12.0 * H;
    let (vol, surface) = slab(NXY, &[(Layer::Cortical, 1500.0, 3e-3), (Layer::Cancellous, 300.0, 6e-3)]);
    let path =
        PlannedPath::new(Point3::new(centre, centre, surface), Point3::new(centre, centre, surface + 9e-3)).unwrap();
    let mut cfg = EngineConfig::new(path);
    cfg.max_sessions = 4;
    cfg.reserve_bricks = 256;
    let (mut core, mut link) = build(&vol, &cfg).unwrap();
    let routes = Routes::new(std::mem::take(&mut link.poses));
    let ids = ["s0", "s1", "s2", "s3"];
    for slot in 0..4u16 {
        routes.assign(slot, 1, ids[usize::from(slot)], std::time::Instant::now());
    }
    routes.publish(ids.iter().enumerate().map(|(slot, id)| (*id, Route { slot: slot as u16, generation: 1 })));
    for slot in 0..4u16 {
        link.commands
            .push(Command::Activate { slot, generation: 1, path: None, mode: GuidanceMode::Shaped, gain: 1.0 })
            .unwrap();
    }
    let pose = |z: f64| Pose {
        position_m: Point3::new(centre, centre, z),
        orientation: UnitQuaternion::identity(),
        drill_on: true,
        spindle_rpm: 1250.0,
    };
    let t0 = std::time::Instant::now();
    let ticker = link.ticker.clone();
    let mut run = |core: &mut bone_sim::engine::TickCore, from: u32, to: u32| {
        for k in from..to {
            let now = t0 + std::time::Duration::from_millis(u64::from(k));
            // Feed from 2 mm above the surface into the bone at 5 mm/s.
            let z = surface - 2e-3 + 5e-3 * f64::from(k) * 1e-3;
            for (slot, id) in ids.iter().enumerate() {
                let msg = PoseMsg { seq: k, client_time_ns: u64::from(k), pose: pose(z + slot as f64 * 0.1e-3) };
                let route = routes.find(id).unwrap();
                routes.pose(route, &msg, std::time::Instant::now()).unwrap();
                if slot % 2 == 1 {
                    // The pose's own thread: ticks the slot and queues what it made.
                    let _ = ticker.tick(slot as u16, 1, now, u64::MAX, true);
                }
            }
            if k % 100 == 50 {
                for slot in 0..4u16 {
                    let cmd = Command::Prediction {
                        slot,
                        generation: 1,
                        window_seq: k,
                        predicted_n: [0.0, 0.0, -0.5],
                        latency_s: 0.005,
                        pose_client_time_ns: u64::from(k),
                    };
                    link.commands.push(cmd).unwrap();
                }
            }
            if k % 1000 == 700 {
                // A bit swap mid-drill (set_drill): 1.0 mm and 1.5 mm burrs in turn.
                let radius_m = if k % 2000 == 700 { 1.0e-3 } else { 1.5e-3 };
                link.commands.push(Command::SetBurr { slot: 2, radius_m }).unwrap();
            }
            if k % 500 == 250 {
                link.commands.push(Command::Snapshot { slot: (k / 500 % 4) as u16 }).unwrap();
            }
            // The tick thread's own entry point, on a synthetic clock: one period per pose.
            core.tick_due(now);
            while link.outputs.pop().is_some() {}
        }
    };
    run(&mut core, 0, 100); // warm-up: first-touch paths
    COUNTING.store(true, Ordering::SeqCst);
    run(&mut core, 100, 3100);
    COUNTING.store(false, Ordering::SeqCst);
    for slot in 0..4 {
        let removed = core.session(slot).unwrap().bone().removed_voxels();
        assert!(removed > 100, "session {slot} never cut bone ({removed} voxels)");
    }
    let on_pose = link.stats.pose_thread_ticks.load(Ordering::SeqCst);
    assert!(on_pose >= 2 * 2900, "only {on_pose} ticks ran on the poses' thread");
    assert_eq!(ALLOCATIONS.load(Ordering::SeqCst), 0, "the tick path allocated");
}
