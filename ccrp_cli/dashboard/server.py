"""`ccrp dashboard`: the real fleet wired to the app, served by uvicorn on a socket bound first
(so the printed URL has the real port, `--bind 127.0.0.1:0` included)."""

from __future__ import annotations

import ipaddress
import logging
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError, printable
from .auth import Auth, allowed_hosts, check_token, new_token
from .events import Broker, Monitor, pki_alerts

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Lifecycle

log = logging.getLogger("ccrp.dashboard")


def parse_bind(bind: str) -> tuple[str, int]:
    """HOST:PORT, [V6]:PORT, or HOST alone (port 8080)."""
    host, port = bind, "8080"
    if bind.startswith("["):
        host, _, rest = bind[1:].partition("]")
        if rest:
            if not rest.startswith(":"):
                raise InputError(f"--bind {bind[:80]!r}: expected HOST:PORT or [IPV6]:PORT")
            port = rest[1:]
    elif bind.count(":") == 1:
        host, port = bind.split(":")
    if not port.isdigit() or int(port) > 65535:
        raise InputError(f"--bind {bind[:80]!r}: the port must be a number from 0 to 65535")
    if host != "localhost":
        try:
            ipaddress.ip_address(host)
        except ValueError:
            raise InputError(f"--bind {bind[:80]!r}: the host must be an IP address or localhost") from None
    return ("127.0.0.1" if host == "localhost" else host), int(port)


def warn_if_exposed(host: str) -> None:
    """One line on stderr when the dashboard listens beyond this machine: it speaks plain HTTP, so
    whoever sees its traffic reads the token in the URL and the cookie in every request."""
    if ipaddress.ip_address(host).is_loopback:
        return
    print(f"ccrp: warning: the dashboard listens on {host}, beyond this machine, without TLS: the token and "
          "the session cookie cross the network in clear; bind it to 127.0.0.1 and reach it through an SSH "
          "tunnel (ssh -L 8080:127.0.0.1:8080 THIS-HOST) or a reverse proxy with TLS (docs/dashboard.md)",
          file=sys.stderr, flush=True)


def results(items: list) -> list[dict]:
    """Per-robot results as `ccrp ... --json` prints them (cli/output.results)."""
    return [{"robot": r.robot, "action": r.action, "seconds": round(r.seconds, 2), "detail": r.detail} for r in items]


def fleet_actions(inventory: Path) -> dict:
    """The page's actions: each opens the fleet as a CLI run does and calls the CLI's own body
    (ccrp_cli.ops: the code map in docs/architecture.md), which takes the fleet lock; the provider it opened is closed after it (a
    cloud's SSH sessions would pile up in a dashboard left running for days)."""
    from contextlib import contextmanager

    from ..fleet import Fleet
    from ..ops.clone import clone_restart as restart, clone_start as start
    from ..ops.fleet import fleet_scale as scale
    from ..ops.robot import robot_power as power
    from ..ops.vpn import vpn_revoke as revoke
    from ..providers import get_provider

    def fresh(what: str, say) -> Fleet:
        fleet = Fleet.open(inventory)
        fleet.store.command = f"dashboard: {what}"
        fleet.store.on_wait = say
        return fleet

    @contextmanager
    def opened(what: str, say):
        fleet = fresh(what, say)
        provider = get_provider(fleet.inventory)
        try:
            yield fleet, provider
        finally:
            provider.close()

    def clone_start(args: dict, say) -> list[dict]:
        with opened(f"clone start {args['robot']}", say) as (fleet, provider):
            return results(start(fleet, provider, args["robot"], say))

    def clone_restart(args: dict, say) -> list[dict]:
        with opened(f"clone restart {args['robot']}", say) as (fleet, provider):
            return results(restart(fleet, provider, args["robot"], say))

    def vpn_revoke(args: dict, say) -> list[dict]:
        with opened(f"vpn revoke {args['robot']}", say) as (fleet, provider):
            records = revoke(fleet, provider, args["robot"], say)
        say(f"revoked {len(records)} certificate(s) of robot {args['robot']!r}; CRL re-issued")
        return [{"cn": r["cn"], "profile": r["profile"], "serial": r["serial"]} for r in records]

    def fleet_scale(args: dict, say) -> list[dict]:
        with opened(f"fleet scale {args['size']}", say) as (fleet, provider):
            return results(scale(fleet, provider, args["size"], say))

    def robot_power(args: dict, say) -> dict:
        r = power(fresh(f"robot power {args['state']} {args['robot']}", say), args["robot"], args["state"], say)
        say(f"{r['robot']}: power {r['power']}, robot {r['robot_state']} (device report {r['reported_at']})")
        return r

    return {"clone-start": clone_start, "clone-restart": clone_restart, "vpn-revoke": vpn_revoke, "fleet-scale": fleet_scale, "robot-power": robot_power}


def teleop_sender(fleet: Fleet, provider: Lifecycle):
    """The drive keys' body: `ccrp robot teleop` (ccrp_cli.ops.robot.robot_teleop) on the fleet the
    dashboard opened: a command changes nothing ccrp records, so it needs no fresh state nor the
    fleet lock."""
    from ..ops.robot import robot_teleop

    def send(robot: str, linear: float, angular: float) -> dict:
        # keep: an operator node stays up on the clone between key presses (evaluation.send_command)
        return robot_teleop(fleet, provider, robot, linear, angular, keep=True)

    def close() -> None:
        from ..robot.evaluation import stop_operators

        stop_operators(fleet, provider)

    return send, close


def camera_functions(fleet: Fleet, provider: Lifecycle):
    """The camera view's bodies on the fleet the dashboard opened, as the drive keys' are (they
    change nothing ccrp records): (read, start). `read` is `ccrp robot camera`'s
    (ccrp_cli.robot.camera.latest_frame) without its start of the agent: the page's GET starts nothing on
    a clone. `start` is the Camera button's POST (ccrp_cli.robot.camera.start_camera)."""
    from ..robot.camera import latest_frame, start_camera

    return (lambda robot: latest_frame(fleet, provider, robot, start=False)), (lambda robot: start_camera(fleet, provider, robot))


def serve(inventory: Path, bind: str, token: str | None, interval: float) -> None:
    import uvicorn

    from ..fleet import Fleet
    from ..providers import get_provider
    from ..ops.status import fleet_status
    from .app import Actions, Camera, Teleop, create_app

    host, port = parse_bind(bind)
    if token is not None:
        check_token(token)
    fleet = Fleet.open(inventory)
    provider = get_provider(fleet.inventory)

    try:
        sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)  # from now on a connection waits in the backlog until uvicorn takes it
    except OSError as exc:
        raise InputError(f"cannot listen on {bind[:80]}: {exc.strerror}") from None
    port = sock.getsockname()[1]

    _log_to_stderr()
    made = token is None
    token = token or new_token()
    auth = Auth(token, port, allowed_hosts(host, port))
    broker = Broker()
    monitor = Monitor(broker, lambda: fleet_status(fleet, provider), lambda robots: pki_alerts(fleet.pki, robots),
                      interval, fleet.name, fleet.inventory.provider.kind, fleet.inventory.ros.ros2)
    runner = Actions(broker, fleet_actions(inventory), monitor.refresh)
    # One provider for the status poll, the drive keys and the camera view (thread-safe as
    # fleet_status's pool needs), closed at shutdown; each action opens and closes its own.
    send, close = teleop_sender(fleet, provider)
    app = create_app(auth, broker, monitor, runner, fleet.name, Teleop(send, broker, close),
                     Camera(*camera_functions(fleet, provider)))

    shown = f"[{host}]" if ":" in host else host
    warn_if_exposed(host)
    url = f"http://{shown}:{port}/"
    # The one place the token is printed: the URL to open, Jupyter style (not when it was given).
    print(f"ccrp: dashboard of fleet {fleet.name!r}, open:\n    {url}?token={token if made else '<your token>'}",
          file=sys.stderr, flush=True)

    config = uvicorn.Config(app, log_config=None, access_log=False, log_level="warning",
                            timeout_graceful_shutdown=2, lifespan="on")
    server = _Server(config, broker)
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()
        monitor.stop()
        provider.close()


class _Printable(logging.Formatter):
    """Log lines as the terminal must show them: a request's path (percent-decoded, so `%1b` is an
    ESC) or a clone's text in a line has its control characters escaped (errors.printable)."""

    def format(self, record: logging.LogRecord) -> str:
        return printable(super().format(record))


def _log_to_stderr() -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Printable("ccrp: dashboard: %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False


def _server_class():
    import uvicorn

    class Server(uvicorn.Server):
        """Ends the event streams first on Ctrl-C, so the shutdown does not wait for open pages."""

        def __init__(self, config, broker: Broker) -> None:
            super().__init__(config)
            self.broker = broker

        def handle_exit(self, sig, frame) -> None:
            self.broker.close()
            super().handle_exit(sig, frame)

    return Server


def _Server(config, broker):  # noqa: N802 - a class made on first use (uvicorn imported late)
    return _server_class()(config, broker)
