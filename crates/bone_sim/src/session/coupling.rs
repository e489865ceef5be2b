//! One tick of the god-object proxy and its coupling to the hand: contact, cutting, removal,
//! heat, and the registration offset where the bone gives way.

use std::f64::consts::TAU;

use nalgebra::{Point3, Vector3};

use super::{DrillingSession, Pose, EMPTY_CAP_KG_M3, GIVE_FRACTION, OFFSET_BLEED, RELEASE_SLACK_M_S};
use crate::contact::CAP_COS;
use crate::record::TICK_S;
use crate::removal::{Burr, Cut};
use crate::volume::layer::Layer;
use crate::volume::rounding;

impl DrillingSession {
    /// One tick of the proxy, removal, thermal and breakthrough models; returns the force the
    /// coupling asks for (before the safety stage).
    pub(super) fn simulate(&mut self, pose: &Pose, dt: f64) -> Vector3<f64> {
        let cfg = &self.config;
        let axis = pose.axis();
        let rpm = if pose.drill_on { pose.spindle_rpm } else { 0.0 };
        let hand_step = pose.position_m - self.prev_stylus_m;
        self.prev_stylus_m = pose.position_m;
        let hand_speed_ax = (hand_step.dot(&axis) / dt).max(0.0);
        let k = cfg.coupling_stiffness_n_per_m;
        let scale = cfg.force_scale();
        let diameter_m = 2.0 * cfg.burr_radius_m;
        let device = pose.position_m - self.offset_m;
        let goal = device - self.proxy_m;
        let push_ax = goal.dot(&axis);
        let zone = self.probe.cutting_zone(&self.bone, &self.proxy_m, &axis);
        let rho = zone.density_kg_m3;
        let cutting = rpm > 0.0 && rho > EMPTY_CAP_KG_M3 && push_ax > 0.0;
        let start_m = self.proxy_m;
        let (mut feed, mut thrust) = (0.0, 0.0);
        if cutting {
            (feed, thrust) = self.feed_into_bone(rpm, push_ax, hand_speed_ax, &zone, &axis, dt);
            let lateral = goal - axis * push_ax;
            self.proxy_m = self.god_move(self.proxy_m, lateral, Some((axis, CAP_COS)), dt);
        } else {
            let moved = self.god_move(self.proxy_m, goal, None, dt);
            self.proxy_m = self.follow_the_hand(moved, hand_step);
        }
        let advance_ax = (self.proxy_m - start_m).dot(&axis);
        let device = pose.position_m - self.offset_m;
        let spring = self.proxy_m - device;
        let push_phys = k * spring.norm() / scale;
        self.remove_bone(rpm, cutting, push_phys, advance_ax, &axis, dt);
        let cfg = &self.config;
        self.recent_density_kg_m3 *= (-advance_ax.abs() / cfg.burr_radius_m).exp();
        // Coupling: spring to the proxy, damping on the relative velocity while apart.
        let v_device = (device - self.prev_device_m) / dt;
        let v_proxy = (self.proxy_m - self.prev_proxy_m) / dt;
        self.tip_velocity_m_s = v_proxy;
        self.prev_device_m = device;
        self.prev_proxy_m = self.proxy_m;
        let apart = spring.norm() > 1e-7;
        let force =
            spring * k + if apart { (v_proxy - v_device) * cfg.coupling_damping_n_s_per_m } else { Vector3::zeros() };

        let torque = if cutting { cfg.cutting.torque_n_m(rpm, feed, rho, diameter_m) } else { 0.0 };
        let thrust = if cutting && feed > 0.0 { thrust } else { 0.0 };
        self.thermal.step(torque, rpm * TAU / 60.0, thrust, feed, dt);
        self.track_breakthrough(rpm, cutting, &zone, &axis);

        self.report(pose, &axis, apart, cutting, &zone, (feed, thrust, torque));
        force
    }

    /// The proxy's advance along the axis while it cuts (the feed the thrust drives through this
    /// bone, released where a cortex gives way); returns the feed (m/s) and the thrust (N).
    fn feed_into_bone(
        &mut self,
        rpm: f64,
        push_ax: f64,
        hand_speed_ax: f64,
        zone: &crate::contact::CuttingZone,
        axis: &Vector3<f64>,
        dt: f64,
    ) -> (f64, f64) {
        let cfg = &self.config;
        let (k, scale, diameter_m) = (cfg.coupling_stiffness_n_per_m, cfg.force_scale(), 2.0 * cfg.burr_radius_m);
        let rho = zone.density_kg_m3;
        // The thrust is the hand's push on the bone: the coupling's stretch, but never more
        // than the device renders along the axis (what the hand actually pushes against).
        let rendered_ax = (-self.limiter.output_n().dot(axis)).max(0.0);
        let thrust = (k * push_ax).min(rendered_ax) / scale;
        let law = &cfg.cutting;
        self.recent_density_kg_m3 = self.recent_density_kg_m3.max(rho);
        let f_law = law.feed_for_thrust_m_s(rpm, thrust, rho, diameter_m);
        // Where a cortex gives way (the cap, and the undrilled bone straight ahead, much
        // softer than the bone the burr has just come through, while it cuts a cortex or
        // plunges out of one), the tip goes no faster than the hand, or than that bone would
        // let this thrust feed it. A cap that reads less bone for other reasons (a burr
        // tilting or wandering on the surface, its own bore) is cut as it comes.
        let recent = self.recent_density_kg_m3;
        let giving_way = self.breakthrough.in_cortex || self.state.plunging;
        let gives = giving_way && zone.ahead_pristine_density_kg_m3 < GIVE_FRACTION * recent;
        let giving = if gives { rho.max(GIVE_FRACTION * recent) } else { rho };
        let f_recent = law.feed_for_thrust_m_s(rpm, thrust, giving, diameter_m);
        let f = f_law.min(f_recent.max(hand_speed_ax));
        let advance = (f * dt).min(push_ax).min(cfg.max_proxy_speed_m_s * dt);
        self.proxy_m += axis * advance;
        let feed = advance / dt;
        if f_law > f {
            // The softer bone resists this feed with less than the stretch pushes: the
            // stretch it no longer holds becomes registration offset, so the force drops to
            // the bone's resistance and the hand, no longer held, carries the tip on.
            let holds_m = law.thrust_n(rpm, feed, rho, diameter_m) * scale / k;
            let released = (push_ax - advance - holds_m).max(0.0);
            self.offset_m += axis * released;
            self.giving |= released > 0.0;
        }
        (feed, thrust)
    }

    /// Removes the bone the spinning burr touches this tick: all it cuts into, or as much of a
    /// lateral contact as the push presses it (`push_phys`, N); a burr that advanced
    /// `advance_ax` (m) along the axis clears what it swept.
    fn remove_bone(&mut self, rpm: f64, cutting: bool, push_phys: f64, advance_ax: f64, axis: &Vector3<f64>, dt: f64) {
        if rpm <= 0.0 {
            return;
        }
        let contact = if cutting { 1.0 } else { (push_phys / self.config.lateral_cut_reference_n).min(1.0) };
        if contact > 0.0 {
            let radius_m = self.probe.cutting_radius_m(self.bone.volume().grid());
            let burr = Burr { center_m: self.proxy_m, radius_m };
            let cut = Cut { spindle_rpm: rpm, dt_s: dt, contact };
            // Burr, cut and axis are valid by construction; an error here would change nothing.
            let _ = if advance_ax > 0.0 {
                self.bone.remove_advancing(&burr, &cut, axis, advance_ax)
            } else {
                self.bone.remove(&burr, &cut)
            };
        }
    }

    /// Writes this tick's pose, contact, layer, depth and cutting figures (feed m/s, thrust N,
    /// torque N·m) into the state.
    fn report(
        &mut self,
        pose: &Pose,
        axis: &Vector3<f64>,
        apart: bool,
        cutting: bool,
        zone: &crate::contact::CuttingZone,
        (feed, thrust, torque): (f64, f64, f64),
    ) {
        let front = self.proxy_m + axis * self.probe.radius_m();
        let s = &mut self.state;
        s.device_m = pose.position_m;
        s.tip_m = self.proxy_m;
        s.axis = *axis;
        s.drill_on = pose.drill_on;
        s.spindle_rpm = pose.spindle_rpm;
        s.in_contact = apart || zone.density_kg_m3 > EMPTY_CAP_KG_M3;
        s.cutting = cutting;
        s.layer = self.bone.volume().layer_at(&front).unwrap_or(Layer::Outside);
        s.depth_m = self.path.depth_m(&self.proxy_m);
        s.deviation_m = self.path.deviation_m(&self.proxy_m);
        s.feed_m_s = feed;
        s.thrust_n = thrust;
        s.torque_n_m = torque;
        s.cutting_density_kg_m3 = zone.density_kg_m3;
    }

    /// Free motion (nothing is cut): the proxy moved from `self.proxy_m` to `moved` towards the
    /// device. It may follow the hand (`hand_step`, the stylus's motion this tick), and slide
    /// along a surface as slowly as a wall erodes, but not leap into a stretch that a surface
    /// stopped holding (the edge of a bone): the part of a move faster than the hand's by more
    /// than [`RELEASE_SLACK_M_S`] becomes registration offset. While the hand withdraws against
    /// the offset, the offset is bled off. Returns where the proxy ends.
    fn follow_the_hand(&mut self, moved: Point3<f64>, hand_step: Vector3<f64>) -> Point3<f64> {
        let from = self.proxy_m;
        let ran = (moved - from).norm();
        let allowed = hand_step.norm() + RELEASE_SLACK_M_S * TICK_S;
        let mut end = moved;
        if ran > allowed {
            // Back off along the path it came, to where it moved only as far as the hand did.
            let candidate = from + (moved - from) * (allowed / ran);
            let probe = |p: &Point3<f64>| self.probe.contact(&self.bone, p, None).points;
            end = if probe(&candidate) <= probe(&from) { candidate } else { from };
            self.offset_m += moved - end;
        }
        // Bleed the offset while the hand withdraws against it in free space.
        let offset = self.offset_m.norm();
        if offset > 0.0 && !self.state.plunging {
            let dir = self.offset_m / offset;
            let back = (-hand_step.dot(&dir)).max(0.0);
            if back > 0.0 && self.probe.contact(&self.bone, &end, None).points == 0 {
                let bleed = (OFFSET_BLEED * back).min(offset);
                self.offset_m -= dir * bleed;
            }
        }
        end
    }

    /// Moves the proxy from `from` by `delta` as far as the bone allows, sliding along surfaces.
    /// A move is refused when it brings more probe points into bone than the proxy already has
    /// (so a proxy that is already embedded can always back out).
    fn god_move(
        &self,
        from: Point3<f64>,
        delta: Vector3<f64>,
        ignore: Option<(Vector3<f64>, f64)>,
        dt: f64,
    ) -> Point3<f64> {
        let len = delta.norm();
        if len < 1e-12 {
            return from;
        }
        let h = self.bone.volume().grid().spacing_m();
        let max_step = 0.25 * h[0].min(h[1]).min(h[2]);
        let reach = len.min(self.config.max_proxy_speed_m_s * dt);
        let steps = rounding::ceil(reach / max_step).clamp(1.0, 16.0);
        let step = delta * (reach / len / steps);
        let mut p = from;
        let mut inside = self.probe.contact(&self.bone, &p, ignore).points;
        for _ in 0..steps as usize {
            let candidate = self.probe.contact(&self.bone, &(p + step), ignore);
            if candidate.points == 0 || candidate.points <= inside {
                p += step;
                inside = candidate.points;
                continue;
            }
            let Some(normal) = candidate.normal() else { break };
            let into = step.dot(&normal);
            let slide = if into < 0.0 { step - normal * into } else { step };
            if slide.norm() < 1e-12 {
                break;
            }
            let slid = self.probe.contact(&self.bone, &(p + slide), ignore);
            if slid.points == 0 || slid.points <= inside {
                p += slide;
                inside = slid.points;
            } else {
                break;
            }
        }
        p
    }
}
