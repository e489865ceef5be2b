"""Where a guided attempt spends its time before the first cortex gives (issue 20): one training
attempt per novice seed, the `dhg study` novice (before any learning), traced at every 10 Hz record.
Prints, per seed, the planned breakthrough depth, the depth at which the cortex gave, the seconds
spent in the warning's span (the last ``warning_span_m`` before the planned breakthrough, cortex not
yet through), and there the feed into bone (percentiles), the median thrust and the axial guidance
share. The figures behind docs/results.md, "A warning for the feed beyond the safe one".

    python tests/benchmarks/warning_zone_trace.py --drill-mm 4.5 --mode shaped --seeds 3,4,5,6,7,8
    python tests/benchmarks/warning_zone_trace.py --drill-mm 4.5 --mode none --seeds 3,4,5,6,7,8
    python tests/benchmarks/warning_zone_trace.py --drill-mm 4.5 --param warning_n=0 --seeds 4,7

The model is queried in padded batches of 16 as the study queries it; the attempt is the first
training attempt of a learner that has not yet learned (the study's starts from its pre-test).
"""

from __future__ import annotations

import argparse

import numpy as np

from dhg import default_phantom
from dhg.core.path import TaskRules
from dhg.learning.torchscript import load_model
from dhg.operators.episodes import drill_episode
from dhg.operators.models import Learner, cue_meaning, operator_style
from dhg.operators.styles import sample_style
from dhg.study.runner import MODEL_BATCH, _LocalStation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="3,4,5,6,7,8")
    ap.add_argument("--drill-mm", type=float, default=4.5)
    ap.add_argument("--mode", default="shaped", help="a guidance mode, or 'none'")
    ap.add_argument("--operator", default="instructed", choices=["impedance", "instructed"])
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="a guidance law, as dhg study")
    ap.add_argument("--duration", type=float, default=240.0)
    args = ap.parse_args()
    from dhg.learning.weights import default_model_path

    model = load_model(default_model_path())
    phantom = default_phantom(voxel_m=0.5e-3)
    params = tuple((k, float(v)) for k, v in (p.split("=", 1) for p in args.param))
    guided = args.mode != "none"
    for seed in (int(s) for s in args.seeds.split(",")):
        station = _LocalStation(phantom, model.profiles, params, args.drill_mm * 0.5e-3)
        station.guide(args.mode if guided else None, 1.0)
        base = operator_style(
            sample_style("novice", np.random.default_rng([seed, 1])), args.operator, np.random.default_rng([seed, 2])
        )
        rng = np.random.default_rng([seed, 1, 1, 1])
        session = station.session
        steps = drill_episode(
            session,
            Learner().style(base),
            rng,
            rules=TaskRules(max_duration_s=args.duration),
            guided=True,
            cue_meaning=cue_meaning(args.operator, args.mode if guided else None),
        )
        rows = []
        try:
            window = next(steps)
            while True:
                s = session.state
                rows.append((s.depth_m, s.breakthroughs, float(np.dot(s.guidance_n, s.axis)), s.feed_m_s, s.thrust_n))
                batch = np.repeat(window[None], MODEL_BATCH, 0)
                window = steps.send(np.asarray(model.predict(batch))[0])
        except StopIteration as done:
            ep = done.value
        _report(seed, session, np.array(rows), ep)


def _report(seed: int, session, r: np.ndarray, ep) -> None:
    at = session.planned_breakthrough_depth_m
    span = session.guidance_params["warning_span_m"]
    depth, bt, share, feed, thrust = r.T
    zone = (depth >= at - span) & (bt == 0)
    gave = depth[np.argmax(bt > 0)] if (bt > 0).any() else float("nan")
    line = f"seed {seed}: planned {at * 1e3:.2f} mm, gave at {gave * 1e3:.2f} mm, {zone.sum() * 0.1:.1f} s in the span"
    if zone.any():
        p10, p50, p90 = np.percentile(feed[zone], [10, 50, 90]) * 1e3
        line += (
            f"; there feed p10/50/90 {p10:.2f}/{p50:.2f}/{p90:.2f} mm/s, thrust p50 {np.median(thrust[zone]):.2f} N,"
            f" axial share mean {share[zone].mean():+.3f} N"
        )
    m = ep.metrics
    print(
        f"{line}; attempt {m['completion_time_s']:.1f} s, reached B {ep.extra['reached_target']:.0f},"
        f" plunge {m['plunge_depth_m'] * 1e3:.2f} mm, > 47 °C {m['time_above_47_s']:.1f} s",
        flush=True,
    )


if __name__ == "__main__":
    main()
