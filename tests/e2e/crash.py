"""A Docker fleet of template robots driven through the CLI and killed mid-`fleet scale`: the trial
of tests/e2e/test_crash_safety.py and of bench/crash_scale.py (which runs many)."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import string
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from tests.conftest import ROOT
from tests.scenarios.backend import free_cidr

LABEL = "ccrp-fleet"
SERVER_KEY = "/etc/openvpn/server/ccrp/keys/server.key"


def free_subnets() -> tuple[str, str, str]:
    """public, common and VPN pool subnets that no Docker network or route of this host overlaps."""
    # 172.26: apart from the ranges the cloud fakes claim networks in (172.27-172.29), which run
    # beside it in a parallel test run.
    return free_cidr("172.26.0.0/16"), free_cidr("10.98.0.0/16"), free_cidr("10.64.0.0/12", prefix=16)


@dataclass
class CrashFleet:
    """A Docker fleet of template robots only, with its own CCRP_HOME, driven through the CLI."""

    name: str
    tmp: Path
    client: object  # docker.DockerClient
    log: list[str] = field(default_factory=list)

    @classmethod
    def create(cls, prefix: str = "crash") -> CrashFleet:
        import docker

        client = docker.from_env(timeout=300)
        name = prefix + "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(6))
        tmp = Path(tempfile.mkdtemp(prefix=f"ccrp-{name}-"))
        public, common, pool = free_subnets()
        inventory = {
            "fleet": name,
            "provider": {"kind": "docker", "public_cidr": public},
            "vpn": {"pool": pool},
            "common": {"cidr": common},
            "robots": [],
            "template": {"prefix": "robot", "max": 20},
        }
        (tmp / "inventory.yaml").write_text(yaml.safe_dump(inventory, sort_keys=False))
        return cls(name=name, tmp=tmp, client=client)

    @property
    def home(self) -> Path:
        return self.tmp / "home"

    @property
    def inventory(self) -> Path:
        return self.tmp / "inventory.yaml"

    def env(self, **extra: str) -> dict[str, str]:
        env = {**os.environ, "CCRP_HOME": str(self.home), **extra}
        env.pop("CCRP_INVENTORY", None)
        return env

    def argv(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "ccrp_cli", *args, "-i", str(self.inventory)]

    def ccrp(self, *args: str, timeout: float = 600, **env: str) -> subprocess.CompletedProcess:
        t0 = time.monotonic()
        proc = subprocess.run(self.argv(*args), cwd=ROOT, env=self.env(**env), capture_output=True, text=True,
                              timeout=timeout)
        self.log.append(f"ccrp {' '.join(args)} -> {proc.returncode} in {time.monotonic() - t0:.1f}s")
        return proc

    def check_call(self, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
        proc = self.ccrp(*args, timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(f"ccrp {' '.join(args)} exited {proc.returncode}: {proc.stderr.strip()[-1500:]}")
        return proc

    def prepare(self) -> None:
        """CA and snapshot (built from ccrp/base:bookworm when it is there: about a minute)."""
        self.check_call("vpn", "init")
        self.check_call("snapshot", "build", timeout=1800)

    # -- what is there --------------------------------------------------------------------------
    def labelled(self, role: str) -> dict:
        return {"label": [f"{LABEL}={self.name}", f"ccrp-role={role}"]}

    def clone_containers(self) -> dict[str, list[str]]:
        """robot -> ["name=status", ...] of its clone containers (more than one is a duplicate)."""
        out: dict[str, list[str]] = {}
        # ignore_removed: a container the killed run was removing may vanish between list and inspect.
        for c in self.client.containers.list(all=True, filters=self.labelled("clone"), ignore_removed=True):
            out.setdefault(c.labels.get("ccrp-robot", "?"), []).append(f"{c.name}={c.status}")
        return out

    def secret_volumes(self) -> list[str]:
        return sorted((v.attrs.get("Labels") or {}).get("ccrp-robot", "?")
                      for v in self.client.volumes.list(filters=self.labelled("secrets")))

    def state_robots(self) -> dict[str, str]:
        """robot -> phase, through ccrp's own loader (raises when state.json does not parse)."""
        from ccrp_cli.store import FleetStore

        return {name: rec.phase for name, rec in FleetStore(self.name, home=self.home).load_state().robots.items()}

    def temp_files(self) -> list[str]:
        root = self.home / self.name
        return sorted(p.name for p in root.iterdir() if p.name.endswith(".tmp")) if root.is_dir() else []

    # -- one trial --------------------------------------------------------------------------------
    def secrets_pushed(self, robots: set[str]) -> bool:
        """Whether a running clone of one of `robots` holds its OpenVPN key yet."""
        for c in self.client.containers.list(filters=self.labelled("clone"), ignore_removed=True):
            if c.labels.get("ccrp-robot") in robots and c.exec_run(["test", "-e", SERVER_KEY]).exit_code == 0:
                return True
        return False

    def kill_scale(self, size: int, delay: float, aimed: bool = False) -> dict:
        """Start `ccrp fleet scale SIZE`, SIGKILL it after `delay` s, or (aimed) as soon as a new
        clone holds its secrets: the moment between pushing them and restarting OpenVPN."""
        before = set(self.state_robots())
        proc = subprocess.Popen(self.argv("fleet", "scale", str(size)), cwd=ROOT, env=self.env(),
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
        t0 = time.monotonic()
        if aimed:
            while proc.poll() is None and time.monotonic() - t0 < 300:
                if self.secrets_pushed(set(self.state_robots()) - before):
                    break
                time.sleep(0.05)
            delay = time.monotonic() - t0
        else:
            time.sleep(delay)
        finished_first = proc.poll() is not None
        if not finished_first:
            os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
        left: dict = {"killed": not finished_first, "exit": proc.returncode, "delay_s": round(delay, 2)}
        if finished_first:
            left["stderr_tail"] = err.decode(errors="replace")[-300:]
        self.log.append(f"ccrp fleet scale {size} killed after {delay:.2f}s" if not finished_first
                        else f"ccrp fleet scale {size} ended before the kill ({proc.returncode})")
        try:
            left["state_robots"] = self.state_robots()
            left["state_parses"] = True
        except Exception as exc:  # noqa: BLE001 - what a user would see is the finding
            left["state_parses"], left["state_error"] = False, f"{type(exc).__name__}: {exc}"
        left["clones"] = self.clone_containers()
        left["temp_files"] = self.temp_files()
        return left

    def converge(self, size: int) -> dict:
        """Run `ccrp fleet scale SIZE --json` to completion and check the fleet it leaves."""
        t0 = time.monotonic()
        proc = self.ccrp("fleet", "scale", str(size), "--json")
        took = time.monotonic() - t0
        out: dict = {"exit": proc.returncode, "convergence_s": round(took, 2),
                     "waited_for_lock": "waiting for ccrp run" in proc.stderr}
        try:
            rows = json.loads(proc.stdout)
            out["actions"] = {r["robot"]: r["action"] for r in rows}
            out["failed"] = {r["robot"]: r["detail"] for r in rows if r["action"] == "failed"}
        except ValueError:
            out["actions"], out["failed"] = {}, {"*": proc.stderr.strip()[-600:]}
        out.update(self.check(size))
        return out

    def check(self, size: int) -> dict:
        problems: list[str] = []
        try:
            state = self.state_robots()
        except Exception as exc:  # noqa: BLE001
            return {"problems": [f"state: {exc}"]}
        if len(state) != size:
            problems.append(f"{len(state)} robots in state, wanted {size}: {sorted(state)}")
        clones = self.clone_containers()
        duplicates = {r: c for r, c in clones.items() if len(c) > 1}
        orphans = sorted(r for r in clones if r not in state)
        orphan_volumes = sorted(r for r in self.secret_volumes() if r not in state)
        missing = sorted(r for r in state if r not in clones)
        problems += [f"duplicate clones of {r}: {c}" for r, c in duplicates.items()]
        problems += [f"orphan clone of {r} (not in state)" for r in orphans]
        problems += [f"orphan secrets volume of {r} (not in state)" for r in orphan_volumes]
        problems += [f"no clone for {r}" for r in missing]
        problems += [f"temp file {name} left in the fleet's store" for name in self.temp_files()]
        status = self.ccrp("status", "--json")
        serving = {}
        if status.returncode != 0:
            problems.append(f"ccrp status --json exited {status.returncode}: {status.stderr.strip()[-300:]}")
        else:
            for row in json.loads(status.stdout):
                ok = row["status"] == "running" and row["phase"] == "ready" and row["master_reachable"]
                serving[row["robot"]] = ok
                if not ok:
                    problems.append(f"{row['robot']} not serving: status={row['status']} phase={row['phase']} "
                                    f"master={row['master_reachable']}")
            if set(serving) != set(state):
                problems.append(f"status shows {sorted(serving)}, state has {sorted(state)}")
        return {"state_robots": state, "clones": clones, "duplicates": duplicates, "orphans": orphans,
                "orphan_volumes": orphan_volumes, "temp_files": self.temp_files(), "problems": problems}

    def trial(self, index: int, size: int, start: int, delay: float, aimed: bool = False) -> dict:
        left = self.kill_scale(size, delay, aimed)
        after = self.converge(size)
        ok = (left.get("state_parses", False) and after["exit"] == 0 and not after["failed"]
              and not after["problems"] and not after["waited_for_lock"])
        return {"trial": index, "aimed": aimed, "from_size": start, "to_size": size,
                "kill_delay_s": left["delay_s"], "left": left, "rerun": after, "ok": ok}

    # -- the end ----------------------------------------------------------------------------------
    def cleanup(self) -> list[str]:
        """`ccrp fleet down`, then everything still labelled with this fleet. Returns what is left."""
        try:
            self.ccrp("fleet", "down", timeout=300, CCRP_LOCK_WAIT="60")
        except Exception as exc:  # noqa: BLE001 - the sweep below still runs
            self.log.append(f"fleet down failed: {exc}")
        flt = {"label": [f"{LABEL}={self.name}"]}
        c = self.client
        for what, items, remove in (
            ("container", lambda: c.containers.list(ignore_removed=True, all=True, filters=flt), lambda o: o.remove(force=True, v=True)),
            ("volume", lambda: c.volumes.list(filters=flt), lambda o: o.remove(force=True)),
            ("network", lambda: c.networks.list(filters=flt), lambda o: o.remove()),
            ("image", lambda: c.images.list(filters=flt), lambda o: c.images.remove(o.id, force=True)),
        ):
            for obj in items():
                try:
                    remove(obj)
                except Exception as exc:  # noqa: BLE001 - keep sweeping
                    self.log.append(f"could not remove {what} {getattr(obj, 'name', obj)}: {exc}")
        left = ([f"container {o.name}" for o in c.containers.list(ignore_removed=True, all=True, filters=flt)]
                + [f"volume {o.name}" for o in c.volumes.list(filters=flt)]
                + [f"network {o.name}" for o in c.networks.list(filters=flt)]
                + [f"image {o.tags or o.id}" for o in c.images.list(filters=flt)])
        shutil.rmtree(self.tmp, ignore_errors=True)
        return left
