"""A BenchMARL task for the auction env: :class:`AuctionTask` (BenchMARL's ``TaskClass`` API).

BenchMARL (``pip install benchmarl``; 1.5.2 pins ``torchrl<0.12``, so it lives in its own venv,
see ``examples/benchmarl_qmix.py``) builds its envs through a task. This one builds
:class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv` on a paper system, vectorised over
``num_envs`` copies (copy ``b`` seeded ``seed + b``), with every robot in one group
``"agents"``. The team reward (spec step 8) is where BenchMARL's algorithms read a group's
reward, ``("agents", "reward")`` (repeated per robot, as in VMAS), so QMIX/VDN mix it, MAPPO's
critic learns it and the logged ``episode_reward`` is the team return. The observation is each
robot's local features, the mixers' ``state`` the global features, and the action mask rides in
``("agents", "action_mask")``, where BenchMARL's discrete policies apply it. Only this module
needs BenchMARL; the env itself runs under the torchrl BenchMARL installs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from benchmarl.environments.common import TaskClass
from torchrl.data import Composite
from torchrl.envs import EnvBase

from mrta_rl.conf_paths import system_file
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
from mrta_rl.envs.view_inputs import resolve_system

GROUP = "agents"


class AuctionTask(TaskClass):
    """The auction on one system; config ``{"system": "system2", "horizon": 1000}``.

    ``system`` names a file of ``conf/system/`` (``system1``, ``system2``, ``random``) or is the
    path of a team yaml (``/path/to/team.yaml``), checked as the Gymnasium view checks it;
    ``horizon`` is the episode length in ticks (also BenchMARL's evaluation ``max_steps``).
    """

    def __init__(self, name: str = "auction", config: dict[str, Any] | None = None) -> None:
        """Check the config (a clear error before BenchMARL builds anything)."""
        config = {"system": "system2", "horizon": 1000, **(config or {})}
        resolve_system(config["system"])  # an unknown name, missing file or bad team: refused here
        if not (isinstance(config["horizon"], int) and config["horizon"] >= 1):
            raise ValueError(f"horizon must be an int >= 1, got {config['horizon']!r}")
        super().__init__(name, config)

    def get_env_fun(
        self, num_envs: int, continuous_actions: bool, seed: int | None, device: Any
    ) -> Callable[[], EnvBase]:
        """A builder of ``num_envs`` copies (copy ``b`` seeded ``seed + b``), on cpu."""
        path = system_file(self.config["system"])
        horizon = self.config["horizon"]

        def make() -> EnvBase:
            system = resolve_system(path)
            core = AuctionEnv(system, AuctionParams(horizon=horizon), num_envs, seed=seed or 0)
            return AuctionTorchRLEnv(core, group_map={GROUP: list(system.robots)})

        return make

    def supports_continuous_actions(self) -> bool:
        """Bids are discrete."""
        return False

    def supports_discrete_actions(self) -> bool:
        """Bids are discrete: ``Categorical(K + 1)`` per robot."""
        return True

    def max_steps(self, env: EnvBase) -> int:
        """One episode: the horizon."""
        return self.config["horizon"]

    def has_render(self, env: EnvBase) -> bool:
        """No rendering."""
        return False

    def group_map(self, env: EnvBase) -> dict[str, list[str]]:
        """``{"agents": [R1, ...]}``."""
        return env.group_map

    def _group_leaf(self, env: EnvBase, leaf: str) -> Composite:
        """The unbatched observation spec reduced to ``(agents, leaf)`` (as BenchMARL's VMAS)."""
        spec = env.full_observation_spec_unbatched.clone()
        for key in list(spec[GROUP].keys()):
            if key != leaf:
                del spec[GROUP][key]
        del spec["state"]
        return spec

    def observation_spec(self, env: EnvBase) -> Composite:
        """Each robot's local features ``(agents, "observation")``."""
        return self._group_leaf(env, "observation")

    def info_spec(self, env: EnvBase) -> Composite | None:
        """No info entries."""
        return None

    def state_spec(self, env: EnvBase) -> Composite | None:
        """The global features ``state``, the mixers' input."""
        return Composite({"state": env.full_observation_spec_unbatched["state"].clone()})

    def action_spec(self, env: EnvBase) -> Composite:
        """``(agents, "action")``."""
        return env.full_action_spec_unbatched

    def action_mask_spec(self, env: EnvBase) -> Composite | None:
        """``(agents, "action_mask")``: BenchMARL's discrete policies mask with it."""
        return self._group_leaf(env, "action_mask")

    @staticmethod
    def env_name() -> str:
        """The env's name in BenchMARL's logs."""
        return "mrta_auction"
