"""The clone services, in the order `fleet up` runs them (clones.py ensure_clone): the settings of
the relay, autostop and knowledge are pushed in this order before the keys, then the API manager,
knowledge and the nodes are applied in this order once the clone serves; `ccrp status` takes each
one's fields. A new service is its class (base.py CloneService) in its own module and one line
here (docs/architecture.md, "Clone services").

Not here: robot power and the camera view. Their agents come with the user-data (power.py, its
unit and socket) or with the first read (camera.py), so `fleet up` pushes nothing for them; and both
modules reach simulated robots, whose module imports the pipeline."""

from __future__ import annotations

from .api_manager import ApiManager
from .autostop import Autostop
from .knowledge import Knowledge
from .base import CloneService
from .sharing import Relay
from .workloads import Nodes

SERVICES: tuple[CloneService, ...] = (Relay(), Autostop(), ApiManager(), Knowledge(), Nodes())
