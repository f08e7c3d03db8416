"""The install space on a clone: the one script whose steps change it (DEPLOY_SH: stage, swap,
rollback, commit, restore), the form it travels in, and the install spaces `ccrp deploy` pushed,
kept in the fleet's state directory so a clone that starts or is made after the deploy gets the
deployed version (ops/clones.py) without a build."""

from __future__ import annotations

import base64
import gzip
import hashlib
import io
import os
import tarfile
from pathlib import Path
from typing import IO, TYPE_CHECKING, cast

from ..errors import CcrpError
from ..render.files import BundleFile
from ..store import atomic_write, ensure_dir

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Reaches

DEPLOY_DIR = "/var/lib/ccrp/deploy"  # root-only (0700): the pushed tar, the previous units, the digest

# On the clone, as root: $1 the action, then its argv words (a digest: hex; node names:
# [a-z][a-z0-9-]*). D: what deploy keeps; W: the install space; U: the units; I: the index.
#   probe [PATH...]     what the clone runs: its workspace digest, the index, a deploy pending on
#                       it, sha256 of PATHs, sha256 and mode of each file of W
#   stage DIGEST|- [delta]
#                       unpack D/DIGEST.tar.b64 (gzipped) into W.new (- : no new workspace; delta:
#                       over a copy of W), setuid/setgid bits stripped, device files and FIFOs
#                       refused; keep the units and index as they are in D/prev, for a rollback
#   begin               D/pending says `nodes`: the units are about to change
#   swap DIGEST         D/pending says `swapping`; W -> W.prev, W.new -> W; D/current says DIGEST;
#                       D/pending says `swapped`
#   rollback N..        the workspace back (D/pending says it was swapped), the units and index of
#                       D/prev back, nodes N restarted and every previous node started; each step
#                       tried, those that failed named (exit 1)
#   commit              forget D/pending; the version this deploy replaced becomes the one kept for
#                       `deploy --rollback`: D/prev (with its digest) -> D/last, W.prev -> W.last
#   last                the kept version: its digest and index; a deploy pending on the clone, and
#                       the digest it runs
#   restore             the kept version back in place as a deploy would put it (stage, swap,
#                       units and index of D/last, enabled; nodes restarted by the caller), so its
#                       check, commit and rollback are a deploy's
# D/pending is there from the moment the clone's software changes until its nodes passed their check
# (commit) or it went back (rollback): a deploy stopped in between (killed, the link lost) leaves it,
# and the next deploy finishes the check, or rolls back, instead of taking the clone as it is.
DEPLOY_SH = r"""set -eu
D=/var/lib/ccrp/deploy W=/opt/ccrp/workspace U=/etc/systemd/system I=/etc/ccrp/workloads.json
act=$1; shift
keep() {  # the current units and index, what a rollback puts back
  rm -rf "$D/prev" "$W.new"
  mkdir -m 0700 "$D/prev"
  for f in "$U"/ccrp-run-*.service "$I"; do
    [ -e "$f" ] || continue
    cp -p "$f" "$D/prev/"
  done
}
relay_types() {  # $1 the install space W replaced
  # The relay loads the workspace's ROS 2 message types once (agent/relay_interfaces.py): when the
  # interface packages changed, it restarts to take the new ones (a running one only).
  if [ -e "$1/share/ccrp/interfaces.json" ] || [ -e "$W/share/ccrp/interfaces.json" ]; then
    cmp -s "$1/share/ccrp/interfaces.json" "$W/share/ccrp/interfaces.json" || systemctl try-restart ccrp-relay.service >/dev/null 2>&1 || true
  fi
}
swap_in() {  # $1 the install space to run, $2 its digest (empty: none, the snapshot's)
  # Each step leaves what a rollback needs: W.prev (empty when there was no workspace) and
  # current.prev (empty when there was no digest) once W and current have moved.
  echo swapping > "$D/pending"
  rm -rf "$W.prev"
  if [ -e "$W" ]; then mv "$W" "$W.prev"; else mkdir "$W.prev"; fi
  if [ -e "$D/current" ]; then mv "$D/current" "$D/current.prev"; else : > "$D/current.prev"; fi
  mv -T "$1" "$W"
  if [ -n "$2" ]; then echo "$2" > "$D/current"; fi
  echo swapped > "$D/pending"
  relay_types "$W.prev"
}
case $act in
probe)
  printf '== current\n'; cat "$D/current" 2>/dev/null || true
  printf '\n== index\n'; cat "$I" 2>/dev/null || true
  printf '\n== pending\n'; cat "$D/pending" 2>/dev/null || true
  printf '\n== digests\n'; [ $# -eq 0 ] || sha256sum "$@" 2>/dev/null || true
  printf '\n== workspace\n'
  if [ -d "$W" ]; then
    cd "$W"
    find . -type f -exec sha256sum {} + 2>/dev/null || true
    printf '== modes\n'
    find . -type f -printf '%m %p\n'
  fi
  ;;
stage)
  mkdir -p -m 0700 "$D"
  keep
  if [ "$1" != - ]; then
    # Unpacked as root, so no file of the tar's may keep a privilege: W.new stays root-only until
    # checked, a device file or FIFO is refused, and setuid and setgid bits go (a 4755 file would
    # come out root's setuid program). templates/docker/software.j2 and software-bake.sh do the same.
    mkdir -p -m 0700 "$W.new"
    # A delta (delta()) holds only the files this clone lacks, and the list of every path of the
    # version (.ccrp-manifest, NUL-separated): the rest comes from the current workspace, and what
    # the version does not have goes.
    if [ "${2:-}" = delta ] && [ -d "$W" ]; then cp -a "$W/." "$W.new/"; fi
    base64 -d "$D/$1.tar.b64" | tar -xz --no-same-owner -C "$W.new" --strip-components=1
    rm -f "$D/$1.tar.b64"
    if [ -e "$W.new/.ccrp-manifest" ]; then
      (cd "$W.new" && find . -mindepth 1 ! -path ./.ccrp-manifest -print0 | LC_ALL=C sort -z) > "$D/have"
      LC_ALL=C sort -z "$W.new/.ccrp-manifest" > "$D/want"
      (cd "$W.new" && LC_ALL=C comm -z -23 "$D/have" "$D/want" | xargs -0 -r rm -rf --)
      rm -f "$W.new/.ccrp-manifest" "$D/have" "$D/want"
    fi
    odd=$(find "$W.new" ! -type f ! -type d ! -type l | head -n 1)
    if [ -n "$odd" ]; then
      rm -rf "$W.new"
      echo "the install space holds ${odd#"$W.new"/}, a device file or FIFO: refused (only files, directories and links)" >&2
      exit 1
    fi
    find "$W.new" -perm /6000 ! -type l -exec chmod ug-s {} +
    chmod 0755 "$W.new"
  fi
  ;;
stage-clean)
  rm -rf "$W.new" "$D/prev" "$D"/*.tar.b64
  ;;
begin)
  echo nodes > "$D/pending"
  ;;
swap)
  swap_in "$W.new" "$1"
  ;;
rollback)
  # Every step is tried, whatever failed before it: a unit that will not enable must not keep the
  # previous nodes from starting. The steps that failed are named at the end.
  set +e
  failed=
  step() { "$@" >/dev/null 2>&1 || failed="$failed, $*"; }
  if [ ! -d "$D/prev" ]; then echo "nothing to roll back to: $D/prev is gone" >&2; exit 1; fi
  case $(cat "$D/pending" 2>/dev/null) in swap*)
    if [ -e "$W.prev" ]; then
      step rm -rf "$W.failed"
      if [ -e "$W" ]; then step mv -T "$W" "$W.failed"; fi
      step mv -T "$W.prev" "$W"
      relay_types "$W.failed"
      step rm -rf "$W.failed"
    fi
    if [ -s "$D/current.prev" ]; then step mv "$D/current.prev" "$D/current"
    elif [ -e "$D/current.prev" ]; then step rm -f "$D/current" "$D/current.prev"; fi
  esac
  for f in "$U"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    n=${f##*/}
    [ -e "$D/prev/$n" ] && continue
    systemctl disable --now "$n" >/dev/null 2>&1
    step rm -f "$f"
  done
  for f in "$D/prev"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    step cp -p "$f" "$U/"
  done
  if [ -e "$D/prev/workloads.json" ]; then step cp -p "$D/prev/workloads.json" "$I"; else step rm -f "$I"; fi
  step systemctl daemon-reload
  for f in "$D/prev"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    step systemctl enable "${f##*/}"
  done
  for n in "$@"; do
    [ -e "$U/ccrp-run-$n.service" ] || continue
    step systemctl restart "ccrp-run-$n.service"
  done
  for f in "$D/prev"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    step systemctl start "${f##*/}"
  done
  rm -f "$D/pending"
  if [ -n "$failed" ]; then echo "steps that failed: ${failed#, }" >&2; exit 1; fi
  ;;
commit)
  rm -f "$D/pending"  # first: the nodes passed their check; the rest is tidying up
  if [ -d "$D/prev" ]; then
    # The version replaced is kept (one: the last two in all). Its workspace is W.prev when this
    # deploy swapped it (then current.prev is its digest), else the current one: no W.last.
    rm -rf "$W.last" "$D/last"
    if [ -e "$D/current.prev" ]; then mv "$D/current.prev" "$D/prev/digest"
    else cat "$D/current" > "$D/prev/digest" 2>/dev/null || : > "$D/prev/digest"; fi
    if [ -e "$W.prev" ]; then mv -T "$W.prev" "$W.last"; fi
    mv -T "$D/prev" "$D/last"
  fi
  rm -rf "$W.prev" "$W.new" "$D/prev" "$D/current.prev"
  ;;
last)
  printf '== digest\n'; cat "$D/last/digest" 2>/dev/null || printf '%s' '-'
  printf '\n== index\n'; cat "$D/last/workloads.json" 2>/dev/null || true
  printf '\n== pending\n'; cat "$D/pending" 2>/dev/null || true
  printf '\n== current\n'; cat "$D/current" 2>/dev/null || true
  ;;
restore)
  if [ ! -d "$D/last" ]; then echo "no previous version is kept on this clone" >&2; exit 1; fi
  keep
  echo nodes > "$D/pending"
  if [ -e "$W.last" ]; then swap_in "$W.last" "$(cat "$D/last/digest")"; fi
  for f in "$U"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    [ -e "$D/last/${f##*/}" ] && continue
    systemctl disable --now "${f##*/}" >/dev/null 2>&1 || true
    rm -f "$f"
  done
  for f in "$D/last"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    cp -p "$f" "$U/"
  done
  if [ -e "$D/last/workloads.json" ]; then cp -p "$D/last/workloads.json" "$I"; else rm -f "$I"; fi
  systemctl daemon-reload
  for f in "$D/last"/ccrp-run-*.service; do
    [ -e "$f" ] || continue
    systemctl enable "${f##*/}" >/dev/null 2>&1
  done
  rm -rf "$D/last"
  ;;
*)
  echo "unknown action $act" >&2; exit 2
  ;;
esac
"""


def script(provider: Reaches, robot: str, action: str, *words: str, timeout: float = 180) -> str:
    rc, out = provider.transport.exec(robot, ["sh", "-c", DEPLOY_SH, "ccrp-deploy", action, *words], timeout=timeout)
    if rc != 0:
        raise CcrpError(f"deploy step {action} failed on robot {robot!r}'s clone: {' '.join(out.split())[-300:]}")
    return out


MANIFEST = ".ccrp-manifest"


def delta(tar: bytes, have: dict[str, tuple[str, str]]) -> bytes:
    """The install space's tar (top directory `workspace/`) with only what a clone lacks: every
    directory and link, the files whose sha256 or mode differ from `have` (./PATH -> (sha256,
    octal mode), what the clone's probe listed), and MANIFEST, every path of the version."""
    src = tarfile.open(fileobj=io.BytesIO(tar))
    out, paths = io.BytesIO(), []
    top = "workspace"
    with tarfile.open(fileobj=out, mode="w") as dst:
        for member in src.getmembers():
            head, _, rest = member.name.strip("/").partition("/")
            if not rest:
                top = head
                dst.addfile(member)
                continue
            path = f"./{rest}"
            paths.append(path)
            if not member.isfile():
                dst.addfile(member)
                continue
            data = cast(IO[bytes], src.extractfile(member)).read()
            if have.get(path) != (hashlib.sha256(data).hexdigest(), f"{member.mode & 0o7777:o}"):
                dst.addfile(member, io.BytesIO(data))
        listing = "".join(f"{p}\0" for p in paths).encode()
        info = tarfile.TarInfo(f"{top}/{MANIFEST}")
        info.size, info.mode = len(listing), 0o600
        dst.addfile(info, io.BytesIO(listing))
    return out.getvalue()


def pushed(tar: bytes) -> str:
    """The install space as each clone gets it: gzipped, then base64 for the transports' text files."""
    return base64.b64encode(gzip.compress(tar, compresslevel=6, mtime=0)).decode()


# The deployed install spaces the fleet keeps: the inventory's and the one before (as each clone
# keeps the version its last deploy replaced).
KEEP = 2


def _saved_path(fleet: Fleet, digest: str) -> Path:
    return fleet.store.root / "deploy" / f"{digest}.tgz.b64"


def save(fleet: Fleet, digest: str, payload: str) -> None:
    """Keep what deploy pushes (0600, as the state), the oldest beyond KEEP dropped."""
    path = _saved_path(fleet, digest)
    ensure_dir(path.parent)
    atomic_write(path, payload)
    os.utime(path)  # the newest, also when it was kept already
    kept = sorted(path.parent.glob("*.tgz.b64"), key=lambda p: p.stat().st_mtime, reverse=True)
    for old in kept[KEEP:]:
        old.unlink(missing_ok=True)


def saved(fleet: Fleet, digest: str) -> str | None:
    """The pushed install space of software `digest`, when a deploy of it is kept."""
    try:
        return _saved_path(fleet, digest).read_text()
    except FileNotFoundError:
        return None


def push(provider: Reaches, robot: str, digest: str, payload: str) -> None:
    """The install space of software `digest` to robot's clone, a root-only file for `stage`."""
    provider.transport.exec(robot, ["mkdir", "-p", "-m", "0700", DEPLOY_DIR], timeout=30)
    provider.transport.push_files(robot, [BundleFile(f"{digest}.tar.b64", payload, 0o600,
                                                     f"{DEPLOY_DIR}/{digest}.tar.b64")], restart=[])


def install(provider: Reaches, robot: str, digest: str, payload: str) -> None:
    """Put a kept install space on a clone before its nodes start (a clone started or made after
    the deploy): staged, swapped and committed at once, since its nodes are then started and
    checked as at any `fleet up`."""
    push(provider, robot, digest, payload)
    for action in (("stage", digest), ("swap", digest), ("commit",)):
        script(provider, robot, *action)
