"""Helpers shared by unit test modules (none of them a fixture: those are in conftest.py)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import types
from pathlib import Path

AGENT = Path(__file__).resolve().parents[2] / "ccrp_cli" / "agent" / "relay.py"


def openssl_verify(pki, cert, crl_check=False):
    args = ["openssl", "verify", "-CAfile", str(pki / "ca.crt")]
    if crl_check:
        args += ["-crl_check", "-CRLfile", str(pki / "crl.pem")]
    return subprocess.run([*args, str(cert)], capture_output=True, text=True)


def load_agent():
    """relay.py runs on a clone with rospy; its Zenoh config needs none of it."""
    stubs = {name: types.ModuleType(name) for name in ("rospy", "rosgraph") if name not in sys.modules}
    sys.modules.update(stubs)
    try:
        spec = importlib.util.spec_from_file_location("ccrp_relay_agent", AGENT)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        for name in stubs:
            sys.modules.pop(name, None)


def write_bag(path: Path, messages: list[tuple[str, int, str]]) -> None:
    """A ROS 1 bag of std_msgs/String messages: (topic, time in ns, text)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    String = store.types["std_msgs/msg/String"]
    with Writer(path) as w:
        conns = {}
        for topic, t, text in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, "std_msgs/msg/String", typestore=store)
            w.write(conns[topic], t, store.serialize_ros1(String(data=text), "std_msgs/msg/String"))


def read_bag(path: Path) -> list[tuple[str, int, str]]:
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    with Reader(path) as r:
        return [(c.topic, t, store.deserialize_ros1(data, c.msgtype).data) for c, t, data in r.messages()]


def write_bag2(path: Path, messages: list[tuple[str, int, str]], storage: str = "mcap") -> None:
    """A rosbag2 storage file (`path`, *.mcap or *.db3) of std_msgs/String messages (topic, time in
    ns, text), as `ros2 bag record` leaves in its directory: written as a bag, its storage file taken."""
    import shutil
    import tempfile

    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.writer import StoragePlugin
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types["std_msgs/msg/String"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "bag"
        with Writer(bag, version=9, storage_plugin=plugin) as w:
            conns = {}
            for topic, t, text in messages:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, "std_msgs/msg/String", typestore=store)
                w.write(conns[topic], t, store.serialize_cdr(String(data=text), "std_msgs/msg/String"))
        (storage_file,) = [p for p in bag.iterdir() if p.name != "metadata.yaml"]
        shutil.copy(storage_file, path)


def read_bag2(path: Path) -> list[tuple[str, int, str]]:
    """The messages of a rosbag2 bag (a directory with its metadata.yaml, or a storage file)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(path) as r:
        return [(c.topic, t, store.deserialize_cdr(data, c.msgtype).data) for c, t, data in r.messages()]
