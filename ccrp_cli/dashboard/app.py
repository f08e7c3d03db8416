"""The dashboard's web application (FastAPI): the page, its events, and the actions it starts.

Routes (all behind auth.Guard):
  GET  /                       the page (its CSRF token in a meta tag)
  GET  /static/{app.js,style.css}
  GET  /events                 server-sent events: `fleet` (rows + alerts, every poll), `action`
  GET  /api/status             the last `fleet` event as JSON
  GET  /api/actions            the actions of this run, newest last
  POST /api/actions/clone-start  {"robot": NAME}   = ccrp clone start --robot NAME
  POST /api/actions/clone-restart {"robot": NAME}  = ccrp clone restart --robot NAME
  POST /api/actions/vpn-revoke   {"robot": NAME}   = ccrp vpn revoke --robot NAME
  POST /api/actions/fleet-scale  {"size": N}       = ccrp fleet scale N
  POST /api/actions/robot-power  {"robot": NAME, "state": "on"|"off"} = ccrp robot power STATE --robot NAME
  POST /api/teleop             {"robot": NAME, "linear": X, "angular": Z}
                               = ccrp robot teleop: answered with the command's latency
  POST /api/logout             ends this page's session (and clears its cookie)
  POST /api/camera/{robot}/start  starts the camera agent on the robot's clone unless it runs
                               (the Camera button): {"robot", "agent": "running"|"started"}
  GET  /api/camera/{robot}     the latest frame of the robot's camera as its clone sees it
                               (image/jpeg, its details in X-CCRP-Frame-* headers); starts nothing:
                               without a camera agent on the clone, 503 {"why": "no-agent"}

A GET changes nothing, on this server or on a clone: a page the guard does not check can make the
browser send one with the session cookie (an <img src> on a page of another server on this host,
which is the same site whatever its port, so the SameSite=Strict cookie goes along); only a POST,
which the guard checks for Origin and CSRF token, starts or changes anything.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import html
import itertools
import json
import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from importlib import resources
from typing import Any, Literal

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from .auth import Auth, Guard
from ..errors import one_line
from .events import SHOWN, Broker, Monitor, sse

log = logging.getLogger("ccrp.dashboard")

STATIC = {"app.js": "text/javascript; charset=utf-8", "style.css": "text/css; charset=utf-8"}
KEEPALIVE_S = 15.0
ACTIONS_KEPT = 50
LINES_KEPT = 200

# An action: (its arguments, a progress callback) -> what it produced (JSON-able).
ActionFn = Callable[[dict, Callable[[str], None]], Any]


class RobotArg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    robot: str = Field(min_length=1, max_length=63, pattern=r"^[a-z0-9][a-z0-9-]*$")


class TeleopArg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    robot: str = Field(min_length=1, max_length=63, pattern=r"^[a-z0-9][a-z0-9-]*$")
    linear: float = Field(ge=-10, le=10, allow_inf_nan=False)
    angular: float = Field(ge=-10, le=10, allow_inf_nan=False)


# Sends one velocity command: (robot, linear, angular) -> what `ccrp robot teleop --json` prints.
TeleopFn = Callable[[str, float, float], dict]


class Teleop:
    """The page's drive keys: commands run beside the actions (an operator does not wait behind a
    fleet scale), at most one in flight per robot; a key pressed meanwhile is refused (409) and the
    page sends the key's latest state when the answer comes, so commands never queue up."""

    def __init__(self, send: TeleopFn, broker: Broker, close: Callable[[], None] | None = None) -> None:
        self.send, self.broker, self.close = send, broker, close
        self.pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="ccrp-dashboard-teleop")
        self.lock = threading.Lock()
        self.busy: set[str] = set()

    def claim(self, robot: str) -> bool:
        with self.lock:
            if robot in self.busy:
                return False
            self.busy.add(robot)
            return True

    def run(self, robot: str, linear: float, angular: float) -> dict:
        try:
            result = {"ok": True, **self.send(robot, linear, angular)}
        except Exception as exc:  # noqa: BLE001 - reported on the page, the server goes on
            result = {"ok": False, "robot": robot, "linear": linear, "angular": angular, "error": one_line(exc, SHOWN)}
        finally:
            with self.lock:
                self.busy.discard(robot)
        result["at"] = _now()
        self.broker.publish("teleop", result)
        return result

    def shutdown(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        if self.close is not None:
            try:
                self.close()
            except Exception as exc:  # noqa: BLE001 - the server is ending: say so, end anyway
                log.warning("teleop operators not stopped: %s", one_line(exc, SHOWN))


# Reads one camera frame, starting nothing: robot -> ccrp_cli.robot.camera.Frame (raises camera.NoFrame,
# "no-agent" when no camera agent runs on the clone; InputError).
CameraFn = Callable[[str], Any]
# Starts the camera agent on the robot's clone unless it runs: robot -> {"robot", "agent"}.
CameraStartFn = Callable[[str], dict]


class Camera:
    """The page's camera view polls every ~2 s, from each open page: one read per robot runs at a
    time (in a thread: it is an exec on the clone), and a request arriving meanwhile gets that
    read's answer rather than starting another. Starting the agent (the Camera button's POST) is
    kept apart from the reads, one start per robot at a time as well."""

    def __init__(self, read: CameraFn, start: CameraStartFn | None = None) -> None:
        self.read, self.starter = read, start
        self.pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="ccrp-dashboard-camera")
        self.running: dict[str, asyncio.Future] = {}
        self.starting: dict[str, asyncio.Future] = {}

    @staticmethod
    async def _once(pool, table: dict, fn, robot: str):
        # Only the event loop's thread touches the tables: no lock.
        future = table.get(robot)
        if future is None:
            future = asyncio.get_running_loop().run_in_executor(pool, fn, robot)
            table[robot] = future
            future.add_done_callback(lambda f: table.pop(robot, None) if table.get(robot) is f else None)
        # A page gone away does not cancel the read another page waits for.
        return await asyncio.shield(future)

    async def frame(self, robot: str):
        return await self._once(self.pool, self.running, self.read, robot)

    async def start(self, robot: str) -> dict:
        return await self._once(self.pool, self.starting, self.starter, robot)

    def shutdown(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


class PowerArg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    robot: str = Field(min_length=1, max_length=63, pattern=r"^[a-z0-9][a-z0-9-]*$")
    state: Literal["on", "off"]


class ScaleArg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: int = Field(ge=0, le=10000)


ARGS = {"clone-start": RobotArg, "clone-restart": RobotArg, "vpn-revoke": RobotArg, "fleet-scale": ScaleArg,
        "robot-power": PowerArg}
TITLES = {"clone-start": "clone start --robot {robot}", "clone-restart": "clone restart --robot {robot}",
          "vpn-revoke": "vpn revoke --robot {robot}",
          "fleet-scale": "fleet scale {size}", "robot-power": "robot power {state} --robot {robot}"}


@dataclass
class Action:
    id: int
    kind: str
    args: dict
    title: str
    state: str = "queued"  # queued | running | done | failed
    lines: list[str] | None = None
    result: Any = None
    error: str | None = None
    started_at: str | None = None
    ended_at: str | None = None

    def public(self) -> dict:
        return {"id": self.id, "kind": self.kind, "args": self.args, "title": self.title, "state": self.state,
                "lines": list(self.lines or []), "result": self.result, "error": self.error,
                "started_at": self.started_at, "ended_at": self.ended_at}


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")


class Actions:
    """Runs the page's actions one at a time in a worker thread (they take the fleet lock, as the
    CLI's do), and publishes each change of an action as an `action` event."""

    def __init__(self, broker: Broker, functions: dict[str, ActionFn], after: Callable[[], None]) -> None:
        self.broker, self.functions, self.after = broker, functions, after
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ccrp-dashboard-action")
        self.ids = itertools.count(1)
        self.lock = threading.Lock()
        self.kept: dict[int, Action] = {}

    def submit(self, kind: str, args: dict) -> Action:
        action = Action(id=next(self.ids), kind=kind, args=args, title=TITLES[kind].format(**args), lines=[])
        with self.lock:
            self.kept[action.id] = action
            while len(self.kept) > ACTIONS_KEPT:
                self.kept.pop(min(self.kept))
        self._publish(action)
        self.pool.submit(self._run, action)
        return action

    def _publish(self, action: Action) -> None:
        with self.lock:
            data = action.public()
        self.broker.publish("action", data)

    def _run(self, action: Action) -> None:
        def say(line: str) -> None:
            with self.lock:
                action.lines.append(" ".join(str(line).split()))
                del action.lines[:-LINES_KEPT]
            self._publish(action)

        action.state, action.started_at = "running", _now()
        self._publish(action)
        log.info("action %d started: %s", action.id, action.title)
        try:
            action.result = self.functions[action.kind](action.args, say)
            failed = _failed_items(action.result)
            action.state = "failed" if failed else "done"
            if failed:
                action.error = "; ".join(failed)
        except Exception as exc:  # noqa: BLE001 - reported on the page, the server goes on
            action.state, action.error = "failed", one_line(exc, SHOWN)
        action.ended_at = _now()
        log.info("action %d %s: %s", action.id, action.state, action.title)
        self._publish(action)
        self.after()

    def list(self) -> list[dict]:
        with self.lock:
            return [a.public() for a in sorted(self.kept.values(), key=lambda a: a.id)]

    def shutdown(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def _failed_items(result: Any) -> list[str]:
    """Per-robot results (as `output.results` renders them) that failed."""
    if not isinstance(result, list):
        return []
    return [f"{r.get('robot')}: {r.get('detail') or 'failed'}" for r in result
            if isinstance(r, dict) and r.get("action") == "failed"]


def _static(name: str) -> bytes:
    return resources.files(__package__).joinpath("static", name).read_bytes()


def create_app(auth: Auth, broker: Broker, monitor: Monitor, actions: Actions, fleet_name: str,
               teleop: Teleop | None = None, camera: Camera | None = None) -> FastAPI:
    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        broker.bind(asyncio.get_running_loop())
        if not monitor.is_alive() and not monitor.stopping.is_set():
            monitor.start()
        try:
            yield
        finally:
            broker.close()
            monitor.stop()
            actions.shutdown()
            if teleop is not None:
                teleop.shutdown()
            if camera is not None:
                camera.shutdown()

    app = FastAPI(lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    page = _static("index.html").decode()

    @app.get("/", response_class=HTMLResponse)
    async def index(request: Request) -> HTMLResponse:
        session = request.scope["ccrp_session"]
        body = (page.replace("{{csrf}}", html.escape(session.csrf, quote=True))
                    .replace("{{fleet}}", html.escape(fleet_name)))
        return HTMLResponse(body)

    @app.get("/static/{name}")
    async def static(name: str) -> Response:
        if name not in STATIC:
            return Response(status_code=404)
        return Response(_static(name), media_type=STATIC[name])

    @app.get("/api/status")
    async def status() -> Response:
        last = broker.last("fleet")
        return Response(last or "null", media_type="application/json")

    @app.get("/api/actions")
    async def list_actions() -> JSONResponse:
        return JSONResponse(actions.list())

    @app.post("/api/actions/{kind}")
    async def start(kind: str, request: Request) -> JSONResponse:
        if kind not in ARGS:
            return JSONResponse({"error": f"no action {kind[:40]!r}"}, status_code=404)
        try:
            args = ARGS[kind].model_validate_json(await request.body())
        except ValueError as exc:
            return JSONResponse({"error": f"bad arguments: {one_line(exc, 200)}"}, status_code=400)
        action = actions.submit(kind, args.model_dump())
        return JSONResponse(action.public(), status_code=202)

    @app.post("/api/logout")
    async def logout(request: Request) -> Response:
        # A POST like the actions: the guard checked Origin and CSRF token, so no other page can
        # log the operator out.
        auth.end(request.scope["ccrp_session"])
        response = Response(status_code=204)
        response.delete_cookie(auth.cookie, path="/", httponly=True, samesite="strict")
        return response

    @app.post("/api/teleop")
    async def drive(request: Request) -> JSONResponse:
        if teleop is None:
            return JSONResponse({"error": "teleoperation is not available here"}, status_code=404)
        try:
            args = TeleopArg.model_validate_json(await request.body())
        except ValueError as exc:
            return JSONResponse({"error": f"bad arguments: {one_line(exc, 200)}"}, status_code=400)
        if not teleop.claim(args.robot):
            return JSONResponse({"error": f"a command to {args.robot} is still on its way"}, status_code=409)
        loop = asyncio.get_running_loop()
        result = await loop.run_in_executor(teleop.pool, teleop.run, args.robot, args.linear, args.angular)
        return JSONResponse(result, status_code=200 if result["ok"] else 502)

    async def camera_call(robot: str, call) -> tuple[Any, JSONResponse | None]:
        """(what `call(robot)` gave, None), or (None, the refusal): a bad name, a robot not in the
        fleet, no frame or no clone (with its `why`), a failed provider."""
        from ..robot.camera import NoFrame
        from ..errors import InputError

        if camera is None:
            return None, JSONResponse({"error": "the camera view is not available here"}, status_code=404)
        try:
            RobotArg(robot=robot)
        except ValueError:
            return None, JSONResponse({"error": f"bad robot name {robot[:40]!r}"}, status_code=400)
        try:
            return await call(robot), None
        except InputError as exc:  # not a robot of this fleet
            return None, JSONResponse({"error": exc.one_line()}, status_code=404)
        except NoFrame as exc:
            return None, JSONResponse({"error": exc.one_line(), "why": exc.why}, status_code=503,
                                      headers={"Cache-Control": "no-store"})
        except Exception as exc:  # noqa: BLE001 - the provider failed: said on the page, the server goes on
            return None, JSONResponse({"error": one_line(exc, SHOWN)}, status_code=502, headers={"Cache-Control": "no-store"})

    @app.post("/api/camera/{robot}/start")
    async def camera_start(robot: str) -> JSONResponse:
        # A POST: the guard checked Origin and CSRF token, so only this server's page starts a unit
        # on a clone.
        if camera is not None and camera.starter is None:
            return JSONResponse({"error": "the camera view is not available here"}, status_code=404)
        started, refused = await camera_call(robot, lambda r: camera.start(r))
        if refused is not None:
            return refused
        return JSONResponse(started, headers={"Cache-Control": "no-store"})

    @app.get("/api/camera/{robot}")
    async def camera_frame(robot: str) -> Response:
        # Reads only (camera.frame never starts the agent): a GET any page can make the browser send.
        frame, refused = await camera_call(robot, lambda r: camera.frame(r))
        if refused is not None:
            return refused
        headers = {"Cache-Control": "no-store", "X-CCRP-Frame-Topic": frame.topic, "X-CCRP-Frame-Seq": str(frame.seq),
                   "X-CCRP-Frame-Size": f"{frame.width}x{frame.height}", "X-CCRP-Frame-Encoding": frame.encoding,
                   "X-CCRP-Frame-Read-Ms": f"{frame.read_ms:g}"}
        if frame.stamp is not None:
            headers["X-CCRP-Frame-Stamp"] = f"{frame.stamp:.3f}"
        if frame.age_ms is not None:
            headers["X-CCRP-Frame-Age-Ms"] = f"{frame.age_ms:g}"
        return Response(frame.jpeg, media_type="image/jpeg", headers=headers)

    @app.get("/events")
    async def events(request: Request) -> StreamingResponse:
        session = request.scope["ccrp_session"]
        queue = broker.subscribe()

        async def stream():
            try:
                yield "retry: 2000\n\n"
                for a in actions.list():
                    yield sse("action", json.dumps(a, default=str, separators=(",", ":")))
                # Ends with its session (expired, logged out), within a keepalive: the page's
                # reconnection then gets the 401 that tells it so.
                while not broker.closed and auth.alive(session):
                    try:
                        item = await asyncio.wait_for(queue.get(), timeout=KEEPALIVE_S)
                    except asyncio.TimeoutError:
                        yield ": keepalive\n\n"
                        continue
                    if item is None:
                        break
                    yield sse(*item)
            finally:
                broker.unsubscribe(queue)

        return StreamingResponse(stream(), media_type="text/event-stream", headers={"x-accel-buffering": "no"})

    return Guard(app, auth)
