"""``dhg live-demo`` (``make demo``): the whole product on one machine.

Starts ``dhg-serve`` (phantom femur, bundled model) as a child process on a free loopback port,
drives it with two virtual novices with the same hand (same seed), one feeling the guidance and one
not, prints their skill metrics and the guidance/latency figures side by side, writes the guided
session's X-ray views and a plot of force, guidance and temperature over time, and stops the server
with SIGTERM, as a person would with Ctrl-C. The server runs the live view (``--view``): its URL is
printed at the start, and a screenshot of the guided novice's page is written as ``view.png``.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np

from dhg.core.features import RECORD_INDEX, TICK_S
from dhg.core.session import ThermalParams
from dhg.live.process import ServerProcess, free_port

__all__ = ["plot_live_runs", "run_live_demo"]


def plot_live_runs(runs: list[Any], out: str | Path, title: str = "") -> Path:
    """PNG of networked runs over time (s): force feedback |F| (N), guidance |G| (N) and drill-tip
    temperature (°C), one colour per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dhg.data.plots import _save

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True, constrained_layout=True)
    for run, colour in zip(runs, ("tab:blue", "tab:orange", "tab:green"), strict=False):
        label = f"{run.skill}, {run.guidance_mode} gain {run.guidance_gain:g}"
        r = run.records
        if len(r):
            force = RECORD_INDEX["force_x_n"]
            axes[0].plot(r[:, 0], np.linalg.norm(r[:, force : force + 3], axis=1), color=colour, label=label)
            axes[2].plot(r[:, 0], r[:, RECORD_INDEX["temperature_c"]], color=colour, label=label)
        if run.guidance:
            tg = np.array([g["tick"] * TICK_S for g in run.guidance])  # session time, as the records' time_s
            gx = np.array([np.linalg.norm(g["guidance_n"]) for g in run.guidance])
            axes[1].plot(tg, gx, color=colour, label=label)
    axes[0].set_ylabel("feedback |F| (N)")
    axes[1].set_ylabel("guidance |G| (N)")
    axes[2].set_ylabel("tip temperature (°C)")
    axes[2].axhline(ThermalParams().necrosis_threshold_c, color="red", lw=0.8, ls="--")
    axes[2].set_xlabel("time (s)")
    axes[0].legend(loc="upper left")
    if title:
        axes[0].set_title(title)
    return _save(fig, out)


def _row(name: str, values: list[str]) -> list[str]:
    return [name, *values]


def _screenshot(view_url: str, client: Any, out: Path) -> str:
    """A screenshot of a session's live page, taken between the runs (the browser's software
    drawing takes no CPU from a drilling novice) while the stylus is held still at its last pose,
    drill off (that keeps the session); what went wrong instead, if it could not."""
    from dhg.view.browser import screenshot_session

    stop = threading.Event()

    def hold() -> None:
        if client.last_pose is None:
            return
        position, orientation = client.last_pose
        while not stop.wait(0.05):
            client.send_pose(position, orientation, False, 0.0)

    holder = threading.Thread(target=hold, daemon=True)
    holder.start()
    try:
        return str(screenshot_session(view_url, client.session_id, out))
    except Exception as exc:  # no Chromium here, a page too slow: the demo's figures still stand
        return f"none ({exc})"
    finally:
        stop.set()
        holder.join()


def _comparison_table(runs: list[Any]) -> Any:
    """The runs' skill metrics and guidance and latency figures side by side, a column per run."""
    from rich.table import Table

    table = Table(title="Virtual novice, same hand: with and without guidance (phantom femur)")
    table.add_column("")
    for run in runs:
        label = f"{run.guidance_mode}, gain {run.guidance_gain:g}" if run.guidance_gain > 0 else "unguided"
        table.add_column(label, justify="right")

    def fmt(key: str, scale: float = 1.0, spec: str = ".2f") -> list[str]:
        return [format(float(r.metrics[key]) * scale, spec) for r in runs]

    table.add_row(*_row("reached B", [str(r.metrics["reached_target"]) for r in runs]))
    table.add_row(*_row("completed (task rules)", [str(r.metrics["completed"]) for r in runs]))
    table.add_row(*_row("time drilling (s)", fmt("completion_time_s", 1, ".1f")))
    table.add_row(*_row("distance to B (mm)", fmt("target_distance_m", 1e3)))
    table.add_row(*_row("mean deviation (mm)", fmt("mean_deviation_m", 1e3)))
    table.add_row(*_row("max deviation (mm)", fmt("max_deviation_m", 1e3)))
    table.add_row(*_row("plunge (mm)", fmt("plunge_depth_m", 1e3)))
    table.add_row(*_row("peak temperature (°C)", fmt("peak_temperature_c", 1, ".1f")))
    table.add_row(*_row("time above 47 °C (s)", fmt("time_above_47_s", 1, ".1f")))
    table.add_row(*_row("force jerk (N/s)", fmt("force_jerk_n_per_s")))
    table.add_row(*_row("guidance messages", [str(r.latency["guidance"]) for r in runs]))
    table.add_row(
        *_row(
            "mean |model cue| (N)",
            [
                f"{np.mean([np.linalg.norm(g['guidance_n']) for g in r.guidance]):.3f}" if r.guidance else "-"
                for r in runs
            ],
        )
    )
    table.add_row(
        *_row(
            "model latency p99 (ms)",
            [
                f"{np.percentile([g['model_latency_s'] for g in r.guidance], 99) * 1e3:.1f}" if r.guidance else "-"
                for r in runs
            ],
        )
    )
    for key, label in (("pose_to_force", "pose→force"), ("pose_to_guidance", "pose→guidance")):
        for q in ("p50", "p99"):
            table.add_row(*_row(f"{label} {q} (ms)", [f"{r.latency[f'{key}_{q}_s'] * 1e3:.2f}" for r in runs]))
    table.add_row(*_row("forces / poses sent", [f"{r.latency['forces']} / {r.poses_sent}" for r in runs]))
    table.add_row(*_row("missed ticks (server)", [str(r.server_health["missed_ticks"]) for r in runs]))
    return table


def run_live_demo(
    out: str | Path,
    duration_s: float = 20.0,
    seed: int = 7,
    echo_server: bool = True,
    zenoh_config_file: str | None = None,
) -> int:
    """Runs the demo (see the module docstring); returns the server's exit code. A
    ``zenoh_config_file`` goes to the server and both trainees (the endpoint stays loopback)."""
    from rich.console import Console

    from dhg.live.client import TraineeClient
    from dhg.live.trainee import run_trainee

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    console = Console()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    console.print(f"[bold]starting dhg-serve[/] on {endpoint} (phantom femur, bundled model)")
    zcfg = ["--zenoh-config", str(zenoh_config_file)] if zenoh_config_file else []
    view_port = free_port()
    view_url = f"http://127.0.0.1:{view_port}"
    server = ServerProcess(
        ["--listen", endpoint, "--status-every", "5", "--view", str(view_port), *zcfg], echo=echo_server
    )
    console.print(
        f"[bold]live view[/]: {view_url} (the instructor's page: open a novice's page from it to watch the drill)"
    )
    runs = []
    shot: str | None = None
    try:
        for name, gain in (("guided", 1.0), ("unguided", 0.0)):
            console.print(f"[bold]{name} novice[/]: drilling for up to {duration_s:g} s (seed {seed}) …")
            with TraineeClient(endpoint, f"demo-{name}", zenoh_config_file=zenoh_config_file) as client:
                run = run_trainee(client, "novice", gain, duration_s, seed)
                if name == "guided":
                    for view, png in client.xray().items():
                        (out / f"{view}.png").write_bytes(png)
                run.server_health = client.health(duration_s + 5.0)
                if name == "guided":
                    shot = _screenshot(view_url, client, out / "view.png")
            runs.append(run)
    finally:
        code = server.stop()
    table = _comparison_table(runs)
    console.print(table)
    plot = plot_live_runs(runs, out / "live.png", "Virtual novice through dhg-serve: guided vs unguided")
    console.print(
        f"X-ray views of the guided session: {', '.join(str(out / f'{v}.png') for v in ('top', 'front', 'side'))}"
    )
    console.print(f"plot: {plot}")
    console.print(f"live view of the guided novice: {shot}")
    console.print(f"dhg-serve exited with code {code}")
    return code
