"""The clone services, in the order `fleet up` runs them (clones.py ensure_clone): the settings of
the relay, autostop and knowledge are pushed in this order before the keys, then the API manager,
knowledge, the nodes and the camera agent are applied in this order once the clone serves; `ccrp status` takes each
one's fields; the user-data writes their units in this order too (boots()). A new service is its
class (base.py CloneService) in its own module and one line here (docs/architecture.md, "Clone
services")."""

from __future__ import annotations

from .api_manager import ApiManager
from .autostop import Autostop
from .base import Boot, CloneService
from .camera import Camera
from .knowledge import Knowledge
from .power import Power
from .sharing import Relay
from .workloads import Nodes

SERVICES: tuple[CloneService, ...] = (Relay(), Autostop(), Power(), ApiManager(), Knowledge(), Nodes(), Camera())


def boots() -> tuple[Boot, ...]:
    """What the services add to a clone's user-data, for render/cloudinit.py (which cannot import
    the services: they import render/)."""
    return tuple(s.boot for s in SERVICES)


def image_agents() -> tuple[str, ...]:
    """The agents a ROS 1 snapshot holds (each service's Boot.image_agents, in this order): what
    `snapshot build` hands the provider's build and `snapshot bake` its builder's user-data, and
    `ccrp deploy` its build in the same image (ops/snapshots.py, ops/deploy.py)."""
    return tuple(a for s in SERVICES for a in s.boot.image_agents)
