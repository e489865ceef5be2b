//! Any control request to any session id, against a running server (no network: a peer that
//! listens on an ephemeral loopback port only): an answer or a refusal, never a panic or a hang.
//! The input is `<id>\n<JSON body>`; bodies that are not JSON are refused before the parser, as
//! the queryable refuses them, so they are skipped here.
#![no_main]

use std::sync::{Arc, Mutex, OnceLock};

use bone_sim::engine::EngineConfig;
use bone_sim::transport::{Server, ServerConfig};
use bone_sim::{Grid, HuMapping, Layer, PlannedPath, Volume};
use libfuzzer_sys::fuzz_target;
use nalgebra::Point3;

fn server() -> &'static Mutex<Server> {
    static SERVER: OnceLock<Mutex<Server>> = OnceLock::new();
    SERVER.get_or_init(|| {
        let (n, h) = (16usize, 1e-3);
        let grid = Grid::axis_aligned([n; 3], [h; 3], [0.0; 3]).expect("a grid");
        let labels = vec![Layer::Cortical.id(); grid.len()];
        let hu = vec![1500f32; grid.len()];
        let volume = Arc::new(Volume::from_hu(grid, &hu, Some(&labels), HuMapping::default()).expect("a volume"));
        let path = PlannedPath::new(Point3::new(0.008, 0.008, 0.0), Point3::new(0.008, 0.008, 0.016)).expect("a path");
        let mut engine = EngineConfig::new(path);
        engine.max_sessions = 4;
        engine.reserve_bricks = 64;
        let config = ServerConfig {
            prefix: "fuzz".into(),
            idle_timeout_s: 0.5,
            model_timeout_s: 0.05,
            zenoh_json5: r#"{"mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                "scouting": {"multicast": {"enabled": false}}}"#
                .into(),
            owners: bone_sim::transport::registry::Owners { names: vec!["s1".into()], max_sessions: 2 },
            tick_on: bone_sim::engine::TickOn::default(),
        };
        Mutex::new(Server::start(&volume, &engine, config).expect("a server"))
    })
}

fuzz_target!(|data: &[u8]| {
    let split = data.iter().position(|&b| b == b'\n').unwrap_or(data.len());
    let Ok(id) = std::str::from_utf8(&data[..split]) else { return };
    let body = data.get(split + 1..).unwrap_or_default();
    let Ok(request) = serde_json::from_slice::<serde_json::Value>(body) else { return };
    let server = server().lock().expect("no earlier panic");
    if let Ok(reply) = server.control(id, &request) {
        assert!(reply.is_object(), "a control reply is a JSON object");
    }
    let _ = server.metrics(id);
});
