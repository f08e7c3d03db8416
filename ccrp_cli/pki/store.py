"""The fleet PKI on disk: $CCRP_HOME/<fleet>/pki/.

    ca.crt  crl.pem  index.json
    relay-ca.crt                                    (the relay links' own CA: see issue_relay)
    private/ca.key  private/relay-ca.key  private/<cn>-<serial>.key      (0600)
    issued/<cn>-<serial>.crt
    tls-crypt/<robot>.key                           (0600, shared by a clone and its robot)
    passwords/<robot>.txt  passwords/<robot>.hash   (0600; only the hash reaches the clone)
    passwords/<robot>.power.txt  ...hash            (the robot's power device, when it has one)

Callers hold the fleet lock (FleetStore.lock) around every mutating call.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

from cryptography import x509
from cryptography.hazmat.primitives import serialization
from pydantic import BaseModel, ConfigDict

from ..errors import CcrpError
from ..models.names import clone_host, power_name, relay_name
from ..store import FILE_MODE, atomic_write, atomic_write_all, ensure_dir, file_identity
from . import profiles
from .secrets import hash_password, new_password, tls_crypt_key, verify_password

CRL_WARN_DAYS = 30


class CertRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    serial: str  # hex, as openssl prints it
    cn: str
    profile: Literal["ca", "relay-ca", "server", "client", "relay", "power"]
    robot: str | None = None
    not_after: dt.datetime
    cert_path: str
    key_path: str
    revoked_at: dt.datetime | None = None

    @property
    def revoked(self) -> bool:
        return self.revoked_at is not None


class PkiIndex(BaseModel):
    model_config = ConfigDict(extra="forbid")

    fleet: str
    key_type: profiles.KeyType
    crl_number: int = 0
    certs: list[CertRecord] = []


class RobotCredentials(BaseModel):
    """Everything secret that a clone and its robot need, loaded from the store."""

    robot: str
    ca_pem: str
    crl_pem: str
    server_cert_pem: str
    server_key_pem: str
    client_cert_pem: str
    client_key_pem: str
    tls_crypt_key: str
    password: str
    password_hash: str
    # The clone's relay certificate and the relay CA (topic sharing over the common network).
    relay_cert_pem: str | None = None
    relay_key_pem: str | None = None
    relay_ca_pem: str | None = None
    # The robot's power device (robot power bundle), when it has one: its own client certificate
    # (CN <robot>.power) and password, for the same clone.
    power_cert_pem: str | None = None
    power_key_pem: str | None = None
    power_password: str | None = None
    power_password_hash: str | None = None


class RobotRevoked(CcrpError):
    """The robot's client certificate was revoked and none was issued since: it stays out."""


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc).replace(microsecond=0)


class PkiStore:
    def __init__(self, root: Path, fleet: str) -> None:
        self.root = root
        self.fleet = fleet
        # index.json as last read or written, with the file's identity then: issuing a fleet's
        # certificates (one robot at a time, each a read-modify-write) parses it once, not once per
        # robot. Atomic writes give the file a new inode, so another run's change is seen.
        self._index: tuple[tuple, PkiIndex] | None = None
        self._lookup_lock = threading.Lock()
        self._lookup_of: tuple[PkiIndex, int, dict, dict] | None = None
        self._relay_cns: tuple[tuple, dict[str, str]] = ((), {})

    # -- paths -----------------------------------------------------------------------------
    @property
    def ca_path(self) -> Path:
        return self.root / "ca.crt"

    @property
    def crl_path(self) -> Path:
        return self.root / "crl.pem"

    @property
    def relay_ca_path(self) -> Path:
        return self.root / "relay-ca.crt"

    @property
    def index_path(self) -> Path:
        return self.root / "index.json"

    def _tls_crypt_path(self, robot: str) -> Path:
        return self.root / "tls-crypt" / f"{robot}.key"

    def _password_paths(self, robot: str) -> tuple[Path, Path]:
        return self.root / "passwords" / f"{robot}.txt", self.root / "passwords" / f"{robot}.hash"

    # -- index -----------------------------------------------------------------------------
    def exists(self) -> bool:
        return self.index_path.exists() and self.ca_path.exists()

    def _identity(self) -> tuple:
        return file_identity(self.index_path.stat())

    def load_index(self) -> PkiIndex:
        """The index (shared with this store's other callers: read it, do not change it; the
        operations below change it through _editing)."""
        if not self.exists():
            raise CcrpError(
                f"the PKI of fleet {self.fleet!r} is not initialised ({self.root})",
                hint="run `ccrp vpn init -i INVENTORY` first",
            )
        with open(self.index_path, "rb") as fh:
            identity = file_identity(os.fstat(fh.fileno()))
            if self._index is None or self._index[0] != identity:
                self._index = (identity, PkiIndex.model_validate_json(fh.read()))
        return self._index[1]

    @contextlib.contextmanager
    def _editing(self) -> Iterator[PkiIndex]:
        """The index to change and save; if the change fails half-way, the copy in memory is no
        longer what the file says, so the next load reads the file again."""
        index = self.load_index()
        try:
            yield index
        except BaseException:
            self._index = None
            raise

    def _save_index(self, index: PkiIndex) -> None:
        atomic_write(self.index_path, index.model_dump_json(indent=2) + "\n")
        self._index = (self._identity(), index)

    def _ca(self, name: str = "ca") -> tuple[x509.Certificate, profiles.PrivateKey]:
        ca_cert = x509.load_pem_x509_certificate((self.root / f"{name}.crt").read_bytes())
        ca_key = serialization.load_pem_private_key((self.root / "private" / f"{name}.key").read_bytes(), None)
        return ca_cert, ca_key  # type: ignore[return-value]

    def _relay_ca(self, index: PkiIndex) -> tuple[x509.Certificate, profiles.PrivateKey]:
        """The CA of relay certificates only, made on first use. Relay links trust it alone, so no
        robot's VPN certificate (stolen or revoked) can open a relay session."""
        if not self._lookup(index)[1].get(("relay-ca", None)):
            key = profiles.generate_key(index.key_type)
            ca = profiles.build_ca(self.fleet, key, name=f"ccrp {self.fleet} relay CA")
            atomic_write(self.root / "private" / "relay-ca.key", profiles.key_pem(key))
            atomic_write(self.relay_ca_path, profiles.cert_pem(ca), mode=0o644)
            index.certs.append(CertRecord(
                serial=format(ca.serial_number, "X"), cn=f"ccrp {self.fleet} relay CA", profile="relay-ca",
                not_after=ca.not_valid_after_utc, cert_path="relay-ca.crt", key_path="private/relay-ca.key",
            ))
        return self._ca("relay-ca")

    # -- operations ------------------------------------------------------------------------
    def init(self, key_type: profiles.KeyType, crl_days: int) -> bool:
        """Create the CA and an empty CRL. Returns False when they already exist."""
        if self.exists():
            # Re-running init also renews a missing or soon-expiring CRL.
            if not self.crl_path.exists() or self.crl_days_left() < CRL_WARN_DAYS:
                with self._editing() as index:
                    self._write_crl(index, crl_days)
            return False
        for sub in ("private", "issued", "tls-crypt", "passwords"):
            ensure_dir(self.root / sub)
        key = profiles.generate_key(key_type)
        ca = profiles.build_ca(self.fleet, key)
        # Key, certificate, CRL, and index.json last: the index marks a complete CA.
        atomic_write(self.root / "private" / "ca.key", profiles.key_pem(key))
        atomic_write(self.ca_path, profiles.cert_pem(ca), mode=0o644)
        index = PkiIndex(fleet=self.fleet, key_type=key_type)
        index.certs.append(
            CertRecord(
                serial=format(ca.serial_number, "X"), cn=ca.subject.rfc4514_string().removeprefix("CN="),
                profile="ca", not_after=ca.not_valid_after_utc, cert_path="ca.crt", key_path="private/ca.key",
            )
        )
        self._write_crl(index, crl_days)
        return True

    def _lookup(self, index: PkiIndex) -> tuple[dict[str, list[CertRecord]], dict[tuple, list[CertRecord]]]:
        """index.certs by CN and by (profile, robot), in issue order. Records are only ever
        appended (revocation marks them), so the lookup grows with the index: finding a robot's
        certificates costs the same in a fleet of 10 or of 1,000 robots."""
        with self._lookup_lock:
            if self._lookup_of is None or self._lookup_of[0] is not index or self._lookup_of[1] > len(index.certs):
                self._lookup_of = (index, 0, {}, {})
            _, seen, by_cn, by_owner = self._lookup_of
            for rec in index.certs[seen:]:
                by_cn.setdefault(rec.cn, []).append(rec)
                by_owner.setdefault((rec.profile, rec.robot), []).append(rec)
            self._lookup_of = (index, len(index.certs), by_cn, by_owner)
            return by_cn, by_owner

    @staticmethod
    def _newest_valid(records: list[CertRecord]) -> CertRecord | None:
        now = _now()
        return next((c for c in reversed(records) if not c.revoked and c.not_after > now), None)

    def current(self, index: PkiIndex, cn: str) -> CertRecord | None:
        """The newest valid (unrevoked, unexpired) certificate for `cn`."""
        return self._newest_valid(self._lookup(index)[0].get(cn, []))

    def current_of(self, index: PkiIndex, profile: str, robot: str) -> CertRecord | None:
        """The newest valid certificate of `profile` belonging to `robot`."""
        return self._newest_valid(self._lookup(index)[1].get((profile, robot), []))

    def revoked_since(self, robot: str, index: PkiIndex | None = None) -> dt.datetime | None:
        """When the robot was revoked, if it was and no client certificate was issued since."""
        index = index or self.load_index()
        issued = [c for c in self._lookup(index)[0].get(robot, []) if c.profile == "client"]
        # The newest one decides: a renewal revokes the older ones but leaves the robot enrolled.
        return issued[-1].revoked_at if issued else None

    def _issue(self, index: PkiIndex, profile: profiles.Profile, cn: str, robot: str, days: int,
               files: list[tuple[Path, bytes | str, int]], ips: tuple[str, ...] = ()) -> CertRecord:
        """A new certificate in the index; its key and certificate go to `files`, for the caller
        to write (atomic_write_all) before the index."""
        ca_cert, ca_key = self._relay_ca(index) if profile == "relay" else self._ca()
        key = profiles.generate_key(index.key_type)
        cert = profiles.build_leaf(profile, cn, key, ca_cert, ca_key, days, ips)
        serial = format(cert.serial_number, "X")
        stem = f"{cn}-{serial[:16]}"
        rec = CertRecord(
            serial=serial, cn=cn, profile=profile, robot=robot, not_after=cert.not_valid_after_utc,
            cert_path=f"issued/{stem}.crt", key_path=f"private/{stem}.key",
        )
        files += [(self.root / rec.key_path, profiles.key_pem(key), FILE_MODE),
                  (self.root / rec.cert_path, profiles.cert_pem(cert), 0o644)]
        index.certs.append(rec)
        return rec

    def issue_robot(self, robot: str, days: int, renew: bool = False, enroll: bool = False,
                    crl_days: int = 30) -> list[tuple[CertRecord, bool]]:
        """Ensure the robot's client cert, its clone's server cert, tls-crypt key and password.

        A revoked robot stays out: only `enroll` (the operator's `vpn issue-cert`) lets it back in,
        with a new password and tls-crypt key, as the old ones went with the revoked certificate.
        `renew` revokes the current certificates and rotates both secrets too, so that each old
        credential fails alone. Returns (record, newly_issued) for the client and server certificate.
        """
        with self._editing() as index:
            since = self.revoked_since(robot, index)
            if since is not None and not (enroll or renew):
                raise self.unenrolled(robot, since)
            files: list[tuple[Path, bytes | str, int]] = []
            out, replaced = self._robot_set(index, robot, days, renew, renew or since is not None, files)
            atomic_write_all(files)
            # The index last: until it names the new certificates, a crash leaves the old set in force.
            if replaced:
                self._write_crl(index, crl_days)
            elif any(new for _, new in out):
                self._save_index(index)
            return out

    @staticmethod
    def unenrolled(robot: str, since: dt.datetime) -> RobotRevoked:
        return RobotRevoked(
            f"robot {robot!r} was revoked on {since:%Y-%m-%d %H:%M} UTC and stays unenrolled",
            hint=f"to let it back in on purpose: ccrp vpn issue-cert -i INVENTORY --robot {robot}",
        )

    def issue_fleet(self, robots: dict[str, str], days: int) -> list[str]:
        """issue_robot and issue_relay for many robots at once (robot -> common-network address),
        as `fleet up` needs them: every file written side by side, the index saved once, so a
        fleet's issue costs the same per robot at 10 or 1,000 robots. Revoked robots are left out
        (`fleet up` reports them). Returns the robots that got something new."""
        from concurrent.futures import ThreadPoolExecutor

        with self._editing() as index:
            files: list[tuple[Path, bytes | str, int]] = []
            changed, enrolled = [], [r for r in robots if self.revoked_since(r, index) is None]
            for robot in enrolled:
                out, _ = self._robot_set(index, robot, days, False, False, files, password=False)
                relay = self._relay(index, robot, robots[robot], days, files)
                if relay or any(new for _, new in out):
                    changed.append(robot)
            # scrypt releases the GIL: the passwords are checked (and new ones hashed) side by side.
            with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
                for made in pool.map(lambda r: self._password_files(r) if self._needs_password(r, False) else [], enrolled):
                    files += made
            atomic_write_all(files)
            if changed:
                self._save_index(index)
            return changed

    def _robot_set(self, index: PkiIndex, robot: str, days: int, renew: bool, rotate: bool,
                   files: list[tuple[Path, bytes | str, int]], password: bool = True,
                   ) -> tuple[list[tuple[CertRecord, bool]], list[CertRecord]]:
        """The robot's certificates and secrets in `index`, new files added to `files`: what is
        missing is made, with `renew` the current certificates are replaced (and returned), with
        `rotate` the password and tls-crypt key too (the password only with `password`)."""
        out, replaced = [], []
        for profile, cn in (("client", robot), ("server", clone_host(robot))):
            rec = self.current(index, cn)
            if rec and renew:
                replaced.append(rec)
                rec = None
            out.append((rec, False) if rec else (self._issue(index, profile, cn, robot, days, files), True))
        now = _now()
        for rec in replaced:
            rec.revoked_at = now
        tc = self._tls_crypt_path(robot)
        if rotate or not tc.exists():
            files.append((tc, tls_crypt_key(), FILE_MODE))
        if password and self._needs_password(robot, rotate):
            files += self._password_files(robot)
        return out, replaced

    def _needs_password(self, robot: str, rotate: bool) -> bool:
        txt, hashed = self._password_paths(robot)
        # A run killed while writing them leaves a pair that does not match: make a new one.
        return rotate or not txt.exists() or not hashed.exists() or \
            not verify_password(txt.read_text().strip(), hashed.read_text().strip())

    def _password_files(self, robot: str) -> list[tuple[Path, bytes | str, int]]:
        txt, hashed = self._password_paths(robot)
        password = new_password()
        return [(hashed, hash_password(password) + "\n", FILE_MODE), (txt, password + "\n", FILE_MODE)]

    def issue_power(self, robot: str, days: int, crl_days: int, renew: bool = False) -> tuple[CertRecord, bool]:
        """Ensure the client certificate and password of the robot's power device (CN
        <robot>.power). A revoked robot gets none until it is enrolled again. `renew` revokes the
        current one and rotates the password. Returns (record, newly_issued)."""
        cn = power_name(robot)
        with self._editing() as index:
            since = self.revoked_since(robot, index)
            if since is not None:
                raise self.unenrolled(robot, since)
            old = self.current_of(index, "power", robot)
            new = old is None or renew
            files: list[tuple[Path, bytes | str, int]] = []
            rec = self._issue(index, "power", cn, robot, days, files) if new else old
            if new or self._needs_password(cn, False):
                files += self._password_files(cn)
            atomic_write_all(files)
            # The index last: until it names the new certificate, a crash leaves the old one in force.
            if new and old is not None:
                old.revoked_at = _now()
                self._write_crl(index, crl_days)  # saves the index
            elif new:
                self._save_index(index)
            return rec, new

    def issue_relay(self, robot: str, common_ip: str, days: int) -> bool:
        """Ensure the relay certificate of robot's clone, valid for its common-network address.
        Each one gets a CN of its own (relay-<robot>-<n>): the agents admit only the CNs of the
        fleet's current relay certificates, so a replaced or revoked one is refused.
        Returns True when one was issued (none yet, the address changed, or an old fleet's
        certificate from the VPN CA)."""
        with self._editing() as index:
            files: list[tuple[Path, bytes | str, int]] = []
            if not self._relay(index, robot, common_ip, days, files):
                return False
            atomic_write_all(files)
            self._save_index(index)
            return True

    def _relay(self, index: PkiIndex, robot: str, common_ip: str, days: int,
               files: list[tuple[Path, bytes | str, int]]) -> bool:
        rec = self.current_of(index, "relay", robot)
        if rec is not None:
            cert = x509.load_pem_x509_certificate((self.root / rec.cert_path).read_bytes())
            ips = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(x509.IPAddress)
            if [str(ip) for ip in ips] == [common_ip] and self.relay_ca_path.exists() and \
                    cert.issuer == x509.load_pem_x509_certificate(self.relay_ca_path.read_bytes()).subject:
                return False
        if rec is not None:
            rec.revoked_at = _now()  # replaced: the agents stop admitting its CN
        generation = 1 + len(self._lookup(index)[1].get(("relay", robot), []))
        self._issue(index, "relay", relay_name(robot, generation), robot, days, files, (common_ip,))
        return True

    def revoke_robot(self, robot: str, crl_days: int, profiles_: tuple[str, ...] = ("client",)) -> list[CertRecord]:
        """Revoke every valid certificate of `robot` of the given profiles and re-issue the CRL."""
        with self._editing() as index:
            now = _now()
            revoked = []
            for rec in index.certs:
                if rec.profile in profiles_ and rec.robot == robot and not rec.revoked:
                    rec.revoked_at = now
                    revoked.append(rec)
            if not revoked:
                raise CcrpError(
                    f"robot {robot!r} has no certificate to revoke ({'/'.join(profiles_)})",
                    hint="`ccrp vpn list -i INVENTORY` shows the issued certificates",
                )
            self._write_crl(index, crl_days)
            return revoked

    def _write_crl(self, index: PkiIndex, days: int) -> None:
        ca_cert, ca_key = self._ca()
        index.crl_number += 1
        # Relay certificates come from the relay CA; relay links admit them by CN, not by this CRL.
        revoked = [(int(c.serial, 16), c.revoked_at) for c in index.certs if c.revoked_at and c.profile != "relay"]
        crl = profiles.build_crl(ca_cert, ca_key, revoked, index.crl_number, days)
        atomic_write(self.crl_path, crl.public_bytes(serialization.Encoding.PEM), mode=0o644)
        self._save_index(index)

    def crl_days_left(self) -> float:
        crl = x509.load_pem_x509_crl(self.crl_path.read_bytes())
        return (crl.next_update_utc - _now()).total_seconds() / 86400

    def credentials(self, robot: str) -> RobotCredentials:
        index = self.load_index()
        client, server = self.current(index, robot), self.current(index, clone_host(robot))
        relay = self.current_of(index, "relay", robot)
        if client is None or server is None:
            raise CcrpError(
                f"robot {robot!r} has no valid certificate",
                hint=f"run `ccrp vpn issue-cert -i INVENTORY --robot {robot}`",
            )
        txt, hashed = self._password_paths(robot)
        read = lambda p: (self.root / p).read_text()  # noqa: E731
        power = self.current_of(index, "power", robot)
        ptxt, phash = self._password_paths(power_name(robot))
        if power is not None and not (ptxt.exists() and phash.exists()):
            power = None  # a device without its password cannot log in: as if it had none
        return RobotCredentials(
            robot=robot,
            ca_pem=self.ca_path.read_text(),
            crl_pem=self.crl_path.read_text(),
            server_cert_pem=read(server.cert_path),
            server_key_pem=read(server.key_path),
            client_cert_pem=read(client.cert_path),
            client_key_pem=read(client.key_path),
            tls_crypt_key=self._tls_crypt_path(robot).read_text(),
            password=txt.read_text().strip(),
            password_hash=hashed.read_text().strip(),
            relay_cert_pem=read(relay.cert_path) if relay else None,
            relay_key_pem=read(relay.key_path) if relay else None,
            relay_ca_pem=self.relay_ca_path.read_text() if relay else None,
            power_cert_pem=read(power.cert_path) if power else None,
            power_key_pem=read(power.key_path) if power else None,
            power_password=ptxt.read_text().strip() if power else None,
            power_password_hash=phash.read_text().strip() if power else None,
        )

    def relay_cns(self) -> dict[str, str]:
        """robot -> CN of its clone's current relay certificate. Every clone's relay config needs
        it: kept until index.json is replaced (atomic writes give it a new inode), so a fleet's
        configs read the index once, not once per clone."""
        if not self.exists():
            self.load_index()  # the one-line error with its hint
        key = self._identity()
        if self._relay_cns[0] != key:
            index = self.load_index()
            robots = {c.robot for c in index.certs if c.profile == "relay" and c.robot}
            self._relay_cns = (key, {r: rec.cn for r in sorted(robots) if (rec := self.current_of(index, "relay", r))})
        return dict(self._relay_cns[1])
