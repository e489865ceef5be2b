//! The pyo3 binding layer, built only with the `python` feature: converts types, maps errors, and
//! releases the GIL around long work. No simulation logic lives here.

// pyo3 extracts arguments such as `PyReadonlyArray2` by value; borrowing them is not an option.
#![allow(clippy::needless_pass_by_value)]

mod convert;
mod errors;
mod server;
mod session;
mod skill;
mod surgeon;
mod volume;

use pyo3::prelude::*;

use crate::record::{FEATURES, RECORD_PERIOD_TICKS, TICK_S};
use crate::removal::{MAX_BURR_RADIUS_M, MIN_BURR_RADIUS_M};
use crate::volume::bricks::BRICK_EDGE;
use crate::volume::layer::Layer;
use crate::volume::material::{HU_MAX, HU_MIN};

/// `dhg._bone_sim`: the native core of DHG. Use it through the `dhg` package.
#[pymodule]
fn _bone_sim(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<volume::PyVolume>()?;
    m.add_class::<volume::PyDrilledVolume>()?;
    m.add_function(wrap_pyfunction!(volume::threshold_layers, m)?)?;
    m.add_class::<session::PySession>()?;
    m.add_class::<server::PyServer>()?;
    m.add_class::<surgeon::PySurgeon>()?;
    m.add_function(wrap_pyfunction!(surgeon::surgeon_constants, m)?)?;
    m.add_function(wrap_pyfunction!(surgeon::axis_quaternion, m)?)?;
    m.add_function(wrap_pyfunction!(server::protocol_layouts, m)?)?;
    m.add_function(wrap_pyfunction!(server::key_layout, m)?)?;
    m.add_function(wrap_pyfunction!(server::check_session_id, m)?)?;
    m.add_function(wrap_pyfunction!(server::check_zenoh_runtime, m)?)?;
    m.add_function(wrap_pyfunction!(server::defaults, m)?)?;
    m.add_function(wrap_pyfunction!(server::control_ops, m)?)?;
    m.add_function(wrap_pyfunction!(server::reply_schemas, m)?)?;
    m.add_function(wrap_pyfunction!(skill::skill_metrics, m)?)?;
    m.add("ERROR_KINDS", crate::error::SimError::KINDS.to_vec())?;
    let flags: Vec<(&str, u16)> = crate::protocol::flags::ALL.to_vec();
    m.add("FLAGS", flags)?;
    m.add("PROTOCOL_VERSION", crate::protocol::VERSION)?;
    m.add("WINDOW_RECORDS", crate::protocol::WINDOW_RECORDS)?;
    m.add("MAX_PAYLOAD_BYTES", crate::protocol::MAX_PAYLOAD_BYTES)?;
    m.add("MAX_QUERY_WINDOWS", crate::protocol::MAX_QUERY_WINDOWS)?;
    m.add("MAX_TICK_ROWS", crate::protocol::MAX_TICK_ROWS)?;
    let features: Vec<&str> = FEATURES.iter().map(|f| f.name).collect();
    let units: Vec<&str> = FEATURES.iter().map(|f| f.unit).collect();
    m.add("FEATURE_NAMES", features)?;
    m.add("FEATURE_UNITS", units)?;
    m.add("RECORD_PERIOD_TICKS", RECORD_PERIOD_TICKS)?;
    m.add("TICK_S", TICK_S)?;
    m.add("POSE_COLUMNS", session::POSE_COLUMNS)?;
    m.add("RECORD_COLUMNS", session::RECORD_COLUMNS)?;
    let names: Vec<&str> = Layer::ALL.iter().map(|l| l.name()).collect();
    m.add("LAYER_NAMES", names)?;
    m.add("HU_MIN", HU_MIN)?;
    m.add("HU_MAX", HU_MAX)?;
    m.add("BRICK_EDGE", BRICK_EDGE)?;
    m.add("FULL_MATERIAL", crate::volume::FULL_MATERIAL)?;
    m.add("DEFAULT_RESERVED_BRICKS", crate::volume::drilled::DEFAULT_RESERVED_BRICKS)?;
    let views: Vec<&str> = crate::xray::View::ALL.iter().map(|v| v.name()).collect();
    m.add("XRAY_VIEWS", views)?;
    m.add("MIN_PATH_LENGTH_M", crate::path::MIN_PATH_LENGTH_M)?;
    m.add("PLAN_STEP_M", crate::session::DrillingSession::PLAN_STEP_M)?;
    m.add("MAX_BURR_RADIUS_M", MAX_BURR_RADIUS_M)?;
    m.add("MIN_BURR_RADIUS_M", MIN_BURR_RADIUS_M)?;
    m.add("MAX_SPINDLE_RPM", crate::session::MAX_SPINDLE_RPM)?;
    let modes: Vec<&str> = crate::guidance::GuidanceMode::ALL.iter().map(|m| m.name()).collect();
    m.add("GUIDANCE_MODES", modes)?;
    m.add("MAX_GAIN", crate::guidance::MAX_GAIN)?;
    m.add("MAX_POSITION_M", crate::session::MAX_POSITION_M)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
