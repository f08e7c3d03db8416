"""ccrp bench ...: the thesis's evaluation on your own fleet (simulated robots on this host)."""

from __future__ import annotations

from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="Measure the fleet: RTT with and without VPN, clone vs shared-server response time, teleoperation.",
                  no_args_is_help=True, rich_markup_mode=None)

STATS = ["MEAN", "P50", "P95", "MAX", "N"]


def _stats(r: dict) -> tuple:
    return tuple("-" if r[k] is None else r[k] for k in ("mean_ms", "p50_ms", "p95_ms", "max_ms")) + (r["samples"],)


@app.command()
def rtt(
    inventory: options.Inventory,
    robot: options.Robot,
    samples: Annotated[int, typer.Option(min=1, max=10_000, help="Round trips per path.")] = 100,
    as_json: options.Json = False,
) -> None:
    """Round trips robot -> clone: ICMP without the VPN (public address), ICMP through the VPN, and
    a ROS topic request/reply through the VPN (ms)."""
    from ..robot.evaluation import rtt as run

    rows = run(options.open_fleet(inventory), robot, samples, output.info)
    output.emit(rows, as_json, ["PATH", "PROBE", "TARGET", *STATS, "LOST"],
                [(r["path"], r["probe"], r["target"], *_stats(r), r["lost"]) for r in rows],
                title=f"round trips of robot {robot!r} in ms (link: {rows[0]['link']})")


@app.command()
def qos(
    inventory: options.Inventory,
    robots: Annotated[str, typer.Option("--robots", help="Robot counts: A..B, A,B,C or N (the fleet's first robots).")] = "1..3",
    task_ms: Annotated[str, typer.Option("--task-ms", help="Task durations in ms, comma-separated.")] = "100,500",
    model: Annotated[str, typer.Option("--model", help="cbm (a clone per robot), pbm (one shared server), or both.")] = "cbm,pbm",
    duration: Annotated[float, typer.Option(min=1, max=3600, help="Seconds of requests per round.")] = 10,
    link: Annotated[str | None, typer.Option("--link", help="Put every robot on this link for the run (as `robot sim --link`); each gets its own back after.")] = None,
    as_json: options.Json = False,
) -> None:
    """Response time of a task as robots are added, clone-based vs proxy-based: every robot sends a
    request each task period (or at once when its last reply came late), all at the same time."""
    from ..robot.evaluation import parse_counts, parse_list, qos as run
    from ..robot.simulated import parse_link

    counts = parse_counts(robots)
    tasks = parse_list(task_ms, None, "--task-ms")
    models = parse_list(model, ("cbm", "pbm"), "--model")
    shaped = parse_link(link) if link is not None else None
    rows = run(options.open_fleet(inventory), counts, tasks, models, duration, shaped, output.info)
    output.emit(rows, as_json, ["MODEL", "ROBOTS", "TASK", "MEAN", "P50", "P95", "N", "LOST"],
                [(r["model"], r["robots"], f"{r['task_ms']:g}", r["mean_ms"], r["p50_ms"], r["p95_ms"], r["samples"], r["lost"])
                 for r in rows], title="response time in ms")


@app.command()
def teleop(
    inventory: options.Inventory,
    robot: options.Robot,
    duration: Annotated[float, typer.Option(min=1, max=3600, help="Seconds to measure.")] = 20,
    as_json: options.Json = False,
) -> None:
    """Teleoperation latency under the robot's current link (`robot sim --link`): velocity commands
    from the clone to the robot, and camera frames (320x240, 5 fps) from the robot to the clone."""
    from ..robot.evaluation import teleop as run

    rows = run(options.open_fleet(inventory), robot, duration, output.info)
    output.emit(rows, as_json, ["STREAM", *STATS, "SENT"],
                [(r["stream"], *_stats(r), r["sent"]) for r in rows], title=f"teleoperation of robot {robot!r} in ms (link: {rows[0]['link']})")
