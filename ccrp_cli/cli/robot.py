"""ccrp robot ...: the robot side (edge bundle, simulated robots)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="The robot side: edge bundle and simulated robots.", no_args_is_help=True, rich_markup_mode=None)


@app.command()
def bundle(
    name: Annotated[str, typer.Argument(help="Robot name.")],
    inventory: options.Inventory,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Directory (default $CCRP_HOME/<fleet>/edge/<robot>).")] = None,
    remote: Annotated[str | None, typer.Option(help="HOST[:PORT] the robot dials (default: its clone's endpoint).")] = None,
) -> None:
    """Write the robot's ready-to-install bundle (same content as `ccrp render edge`)."""
    from ..robot.robots import write_edge

    fleet = options.open_fleet(inventory)
    path = write_edge(fleet, name, out or fleet.store.root / "edge" / name, remote)
    output.info(f"bundle for robot {name!r} in {path}; on the robot: `sudo ./install.sh`")
    typer.echo(str(path))


@app.command()
def sim(
    inventory: options.Inventory,
    robot: Annotated[str | None, typer.Option("--robot", "-r", help="Robot name (with --stop and no --robot: every simulated robot of the fleet).")] = None,
    stop: Annotated[bool, typer.Option("--stop", help="Stop and remove the simulated robot.")] = False,
    wait: Annotated[float, typer.Option("--wait", help="Seconds to wait until the robot's VPN is up and its node is on its clone's master (0: don't wait).")] = 0,
    network: Annotated[str | None, typer.Option("--network", callback=options.cloud_name, help="Docker network of this host the robot runs on (cloud fleets; default `bridge`). Docker and libvirt fleets: their own network, unless a libvirt fleet forwards its VPN ports (provider.vpn_forward): then the robot may be outside.")] = None,
    link: Annotated[str | None, typer.Option("--link", help="Emulate the path to the clone: eu (50 ms round trip), us (180 ms), DELAY_MS[/JITTER_MS[/LOSS_PCT]], or none. On a running robot only the link changes.")] = None,
    as_json: options.Json = False,
) -> None:
    """Run a simulated robot (a container on this host) with exactly its edge bundle; it dials its
    clone over the public network as a real robot would."""
    from ..robot.simulated import Sims, parse_link

    if robot is None and not stop:
        raise typer.BadParameter("--robot is required (only --stop works on every simulated robot at once)", param_hint="'--robot'")
    shaped = parse_link(link) if link is not None else None  # bad --link: exit 2 before anything runs
    fleet = options.open_fleet(inventory)
    sims = Sims(fleet)
    if stop and robot is None:
        from concurrent.futures import ThreadPoolExecutor

        names = sims.names()
        with ThreadPoolExecutor(max_workers=8) as pool:  # each shuts down for a second or two
            list(pool.map(sims.stop, names))
        output.info(f"removed {len(names)} simulated robot(s) of fleet {fleet.name!r}" + (f": {', '.join(names)}" if names else ""))
        return
    fleet.robot(fleet.store.load_state(), robot)
    if stop:
        removed = sims.stop(robot)
        output.info(f"simulated robot {robot!r} {'removed' if removed else 'was not running'}")
        return
    if link is not None and sims.running(robot):
        sims.set_link(robot, shaped)
        output.info(f"simulated robot {robot!r}: link {shaped or 'removed'}")
        result = {"robot": robot, "link": str(shaped) if shaped else None}
    else:
        result = sims.start(robot, network, wait, output.info)
        if shaped is not None:
            sims.set_link(robot, shaped)
            output.info(f"simulated robot {robot!r}: link {shaped}")
        result["link"] = str(shaped) if shaped else None
    if as_json:
        output.emit_json(result)


@app.command()
def teleop(
    inventory: options.Inventory,
    robot: options.Robot,
    linear: Annotated[float, typer.Option("--linear", help="Forward velocity, m/s (geometry_msgs/Twist linear.x).")] = 0.0,
    angular: Annotated[float, typer.Option("--angular", help="Turn rate, rad/s (angular.z).")] = 0.0,
    topic: Annotated[str, typer.Option("--topic", help="The robot's velocity topic on its clone's master.")] = "cmd_vel",
    timeout: Annotated[float, typer.Option("--timeout", min=0.5, max=60, help="Seconds to wait for the robot.")] = 5.0,
    as_json: options.Json = False,
) -> None:
    """Send one velocity command to the robot through its clone (published on the clone's master,
    as an operator's node there would) and report its latency: clone publish -> robot receipt,
    and the round trip to the robot's acknowledgement on <topic>/ack (docs/dashboard.md)."""
    from ..ops.robot import robot_teleop
    from ..robot.evaluation import check_command
    from ..providers import get_provider

    check_command(linear, angular, topic)  # bad input: exit 2 before the fleet is opened
    fleet = options.open_fleet(inventory)
    r = robot_teleop(fleet, get_provider(fleet.inventory), robot, linear, angular, topic, timeout)
    ms = lambda v: "-" if v is None else f"{v:g}"  # noqa: E731
    output.emit(r, as_json, ["ROBOT", "TOPIC", "LINEAR", "ANGULAR", "ACKNOWLEDGED", "ONE WAY MS", "ROUND TRIP MS", "REQUEST MS"],
                [(r["robot"], r["topic"], f"{r['linear']:g}", f"{r['angular']:g}", "yes" if r["acknowledged"] else "no (robot sends no ack)",
                  ms(r["one_way_ms"]), ms(r["round_trip_ms"]), ms(r["request_ms"]))])


@app.command()
def power(
    action: Annotated[str, typer.Argument(help="on, off, status, or bundle.", metavar="on|off|status|bundle")],
    inventory: options.Inventory,
    robot: options.Robot,
    timeout: Annotated[float, typer.Option("--timeout", min=1, max=300, help="Seconds to wait for the device's report.")] = 30.0,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="bundle: directory (default $CCRP_HOME/<fleet>/power/<robot>).")] = None,
    remote: Annotated[str | None, typer.Option(help="bundle: HOST[:PORT] the device dials (default: the clone's endpoint).")] = None,
    as_json: options.Json = False,
) -> None:
    """Switch the robot's power through its power device and wait until the device reports the
    robot off or running (on, off), or read its last report (status). The device sits on the
    robot's power line with a VPN client of its own to the robot's clone, and reports every 3 s;
    `bundle` writes what it installs (its certificate and password are issued then). A simulated
    robot gets a simulated device at its first `robot power` (docs/dashboard.md, Robot power)."""
    from ..errors import InputError
    from ..robot.power import ACTIONS

    if action not in ACTIONS:
        raise InputError(f"robot power {action[:20]!r}: choose on, off, status or bundle", hint="ccrp robot power on --robot R")
    if action != "bundle" and (out or remote):
        raise InputError("--out and --remote go with `robot power bundle`", hint=f"ccrp robot power bundle --robot {robot}")
    fleet = options.open_fleet(inventory)
    if action == "bundle":
        from ..robot.power import write_device_bundle
        from ..providers import get_provider

        path = write_device_bundle(fleet, get_provider(fleet.inventory), robot, out or fleet.store.root / "power" / robot,
                                   remote, output.info)
        output.info(f"bundle for the power device of robot {robot!r} in {path}; on the device: `sudo ./install.sh`, "
                    "then set CCRP_POWER_RELAY_COMMAND in /etc/ccrp/power.env")
        typer.echo(str(path))
        return
    from ..ops.robot import robot_power

    r = robot_power(fleet, robot, action, output.info, timeout)
    state = r["robot_state"] + (f" (device silent for {r['age_s']:.0f} s)" if r["silent"] else "")
    output.emit(r, as_json, ["ROBOT", "POWER", "ROBOT STATE", "REPORTED AT", "SECONDS", "DEVICE"],
                [(r["robot"], r["power"], state, r["reported_at"], f"{r['seconds']:g}", r["device"])])


@app.command()
def camera(
    inventory: options.Inventory,
    robot: options.Robot,
    out: Annotated[Path, typer.Option("--out", "-o", help="The JPEG file to write.")],
    topic: Annotated[str, typer.Option("--topic", help="The robot's camera topic on its clone's master (sensor_msgs/Image).")] = "/camera/image_raw",
    timeout: Annotated[float, typer.Option("--timeout", min=0.5, max=60, help="Seconds to wait for a frame.")] = 3.0,
    as_json: options.Json = False,
) -> None:
    """Write the latest frame of the robot's camera, as its clone sees it, to a JPEG file (asked of a
    camera agent on the clone, which this command starts when none runs; the dashboard's camera view;
    docs/dashboard.md)."""
    from ..robot.camera import check_topic, latest_frame
    from ..errors import cannot_write
    from ..providers import get_provider

    check_topic(topic)  # bad input: exit 2 before the fleet is opened
    fleet = options.open_fleet(inventory)
    frame = latest_frame(fleet, get_provider(fleet.inventory), robot, topic, timeout)
    with cannot_write(out):
        out.write_bytes(frame.jpeg)
    r = {**frame.public(), "out": str(out)}
    ms = lambda v: "-" if v is None else f"{v:g}"  # noqa: E731
    output.emit(r, as_json, ["ROBOT", "TOPIC", "SIZE", "ENCODING", "SEQ", "AGE MS", "READ MS", "BYTES", "OUT"],
                [(r["robot"], r["topic"], f"{r['width']}x{r['height']}", r["encoding"], r["seq"], ms(r["age_ms"]),
                  ms(r["read_ms"]), r["bytes"], r["out"])])
