"""What a snapshot holds of ccrp's agents is the services' to say (render/boot.py Boot.image_agents,
bare_agents; issue 26): the core hands the list to the provider's build (LocalBuild.build_snapshot),
the bake's builder user-data and deploy's build, so no provider reads a core list of them; the
Docker image copies exactly the agents it is given."""

from __future__ import annotations

import yaml

from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.providers.base import SnapshotRecord
from ccrp_cli.resources import agent_source
from ccrp_cli.services.registry import SERVICES, boots, image_agents
from tests.conftest import LAB


def test_the_services_say_which_agents_a_snapshot_and_a_bare_clone_hold():
    declared = {s.name: (s.boot.image_agents, s.boot.bare_agents) for s in SERVICES if s.boot.image_agents}
    assert declared == {"relay": (("relay",), ("relay",)), "api_manager": (("api_manager",), ())}
    assert image_agents() == ("relay", "api_manager")  # in the registry's order
    for s in SERVICES:  # a bare clone gets, of a snapshot's agents, those fleet up does not push
        assert set(s.boot.bare_agents) <= set(s.boot.image_agents), s.name


class Builder:
    """A provider with Ability.LOCAL_BUILD that keeps what build_snapshot was given."""

    kind = "docker"

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def build_snapshot(self, repo, distro, plat, agents, software, digest, bare, progress) -> SnapshotRecord:
        self.calls.append((repo, distro, agents, digest, bare))
        return SnapshotRecord(id="sha256:1", name=f"{repo}:1", created="2026-11-26T00:00:00Z", source="build")


def test_snapshot_build_hands_the_provider_the_services_agents(ccrp_home):
    from ccrp_cli.ops import snapshots

    fleet = Fleet.open(LAB)
    provider = Builder()
    snapshots.build(fleet, provider, lambda m: None)
    snapshots.build(fleet, provider, lambda m: None, bare=True)
    assert provider.calls == [("ccrp/lab-clone", "noetic", ("relay", "api_manager"), "none", False),
                              ("ccrp/lab-clone", "noetic", ("relay", "api_manager"), "none", True)]


def test_the_docker_image_copies_the_agents_it_is_given_and_no_other(monkeypatch):
    from ccrp_cli.providers.docker import images, wheels
    from ccrp_cli.recipes import platform

    plat = platform("noetic", "debian-bookworm")
    monkeypatch.setattr(wheels, "fetch", lambda pip, platforms: {"wheels/x.whl": b"w"})
    text = images.dockerfile("lab", "noetic", images.DEFAULT_BASE, plat, agents=("relay", "camera"))
    assert "COPY relay.py camera.py /usr/local/lib/ccrp/\n" in text and "api_manager.py" not in text
    context = images.build_context(plat, distro="noetic", agents=("relay", "camera"))
    assert {k: v for k, v in context.items() if k.endswith(".py")} == {
        "relay.py": agent_source("relay").encode(), "camera.py": agent_source("camera").encode()}
    bare = images.dockerfile("lab", "noetic", images.DEFAULT_BASE, plat, agents=())
    assert "/usr/local/lib/ccrp/\n" not in bare and ".py" not in "".join(images.build_context(plat, agents=()))


def test_the_bake_and_a_bare_clone_install_the_agents_the_services_declare(lab):
    from ccrp_cli.render import cloudinit

    paths = lambda files: [f["path"] for f in files if f["path"].endswith(".py")]  # noqa: E731
    builder = yaml.safe_load(cloudinit.builder_user_data(lab.inventory, "0123456789abcdef", image_agents()))
    assert paths(builder["write_files"]) == ["/usr/local/lib/ccrp/relay.py", "/usr/local/lib/ccrp/api_manager.py"]
    view = clone_view(lab, lab.load_allocated(), "nao1")
    bare = cloudinit.user_data_dict(view, boots(), install_packages=True)
    snap = cloudinit.user_data_dict(view, boots())
    # The bare clone's user-data adds the relay alone: the API manager comes with fleet up.
    assert sorted(set(paths(bare["write_files"])) - set(paths(snap["write_files"]))) == ["/usr/local/lib/ccrp/relay.py"]
