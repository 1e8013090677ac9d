"""Learner: the one interface every allocation policy implements, fixed, tabular or neural.

The runner (``mrta_rl.runners``) drives every learner with the same loop over the batched
auction env (``docs/spec/auction_env.md``)::

    view = learner.encode(env)                       # decision point of tick t
    actions = learner.act(view, env.action_mask, explore=True)
    result = env.step(actions)
    next_view = learner.encode(env)                  # decision point of tick t + 1
    learner.update(view, actions, result, next_view, env.action_mask)
    # when every copy is done: read env.stats, env.reset(), learner.end_episode()

Learners never build envs and envs never import learners: the runner builds the env (with the
partition's ``Lambda_i`` when :attr:`Learner.requires_partition`) and hands it to the learner's
constructor, which may read its sizes (robots, types, slots, active tasks). The batch size is not
fixed: :meth:`Learner.encode`, :meth:`Learner.act` and :meth:`Learner.update` must work for any
``B``, because the runner evaluates on a separate env with the evaluation batch size (same system,
parameters and active tasks) and reads ``B`` from the arrays it passes.
"""

from __future__ import annotations

import functools
import inspect
from abc import ABCMeta, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from mrta_rl.checked_files import read_yaml
from mrta_rl.conf_paths import learner_block, learner_files, learner_settings
from mrta_rl.config import (
    RUNNER_ARGUMENTS,
    ConfigError,
    UserError,
    check_keywords,
    declared_keywords,
    short_list,
)
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.learners.resources import MemoryQuery, ResourceEstimate
from mrta_rl.loops import NO_TRAINING, NUMPY_LOOP, TORCH_LOOP  # noqa: F401 - for plugins
from mrta_rl.partition import Partition
from mrta_rl.run_layout import RunDirError, check_schema, read_json

LearnerKind = Literal["fixed", "tabular", "neural", "search"]


def read_description(path: Path, schema: dict[str, Any]) -> dict[str, Any]:
    """A learner's ``learner.json`` (what its ``save`` wrote beside its state), checked.

    Args:
        path: The file.
        schema: What ``save`` writes (``run_layout.check_schema``'s form).

    Returns:
        The content.

    Raises:
        RunDirError: naming the file and the key, if it is not such a description.
    """
    try:
        description = read_json(path)
        check_schema(description, schema, path, "")
    except RunDirError as err:
        detail = str(err).removeprefix(f"{path}: ")
        raise RunDirError(f"{path}: not a learner description written by save ({detail})") from None
    return description


class NonFiniteState(UserError):
    """An update made a learner's state NaN or infinite (or out of its range): training stops.

    The learner raises it where the update is made, before the state is kept or saved, so the
    run ends with its last checkpoint as it was; the message names the learner and the step.
    """

    def __init__(self, fault: str) -> None:
        super().__init__(
            f"{fault}; training stopped, nothing of it saved (the last checkpoint stays)"
        )


# what every concrete learner class answers for (besides its own ``label``, see Learner)
@dataclass(frozen=True)
class TrainingTeam:
    """What a learner's settings must fit (:meth:`Learner.check_settings`)."""

    env: AuctionEnv  # an env of the team (the runner's probe: its sizes, not its copies)
    partition: Partition | None  # the subG partition, or None
    copies: int  # training copies B


FACTS = ("kind", "training_loop", "estimate_memory", "learning_space_dimension")


@functools.cache
def _yaml_defaults(target: str) -> tuple[Path | None, dict[str, Any]]:
    """The shipped learner file whose own ``_target_`` is ``target``, and its settings.

    A file that extends another (its defaults list) is the class's only if it names the class
    itself; its settings are then those it composes (``conf_paths.learner_block``).

    Raises:
        ConfigError: naming the files, if more than one names the class.
    """
    files = learner_files()
    own = [name for name, path in files.items() if _own_target(path) == target]
    if len(own) > 1:
        names = short_list(f"learner/{name}.yaml" for name in own)
        raise ConfigError(
            f"{target}: {names} all name this class, so its defaults are ambiguous: give it "
            "every setting, or keep one yaml per class"
        )
    if not own:
        return None, {}
    return files[own[0]], learner_settings(learner_block(own[0], files))


def _own_target(path: Path) -> Any:
    """The ``_target_`` a learner file names itself (None: it names none, or inherits it)."""
    block = read_yaml(path)
    return block.get("_target_") if isinstance(block, dict) else None


class LearnerType(ABCMeta):
    """The type of the learner classes: a learner built without some settings takes its yaml's.

    The yaml of ``conf/learner/`` that names a class is the one home of its defaults
    (:meth:`Learner.defaults`); the class declares each setting, with no default. Calling a
    class with some settings left out (``QMIXLearner(env=env, rng=rng)``) fills them in from
    that yaml before ``__new__`` and ``__init__`` run; the runner passes every setting of the
    run's config, so a run takes exactly its config's values.
    """

    def __call__(cls, *args: Any, **keywords: Any) -> Any:
        """Build a learner; the settings not given are its yaml's (:meth:`Learner.defaults`)."""
        if any(name not in keywords for name in declared_keywords(cls)):
            keywords = {**cls.defaults(), **keywords}
        return super().__call__(*args, **keywords)


class Learner(metaclass=LearnerType):
    """Base class of every learner; subclasses implement at least :meth:`act`.

    Hyperparameters are typed keyword-only ``__init__`` arguments without defaults, so the
    signature is the schema of ``conf/learner/<name>.yaml``; ``Annotated`` ranges and choices
    complete the declaration (``mrta_rl.config``), checked before ``__init__`` runs. The defaults
    are the yaml's, its one home (:meth:`defaults`): a learner built in Python with some
    settings left out takes the yaml's values of those (:class:`LearnerType`). Settings that
    must agree with each other or with the team are checked by :meth:`check_settings`, which the
    runner calls before it builds anything. A learner with epsilon-greedy exploration exposes its
    current value as a float attribute ``epsilon``; the runner shows it when present.

    Every concrete learner class answers for its own facts, so that the runner, the memory
    check, the reports and the benchmarks ask the class and keep no list of learners (as
    BenchMARL's algorithm configs answer ``on_policy()``). A class that lacks one fails when it
    is created (:meth:`__init_subclass__`); a base class that leaves them to its subclasses is
    declared with ``class MyBase(Learner, abstract=True)``. The facts:

    * ``label``: the display name in reports (``subG-CQL``), declared by the class itself (a
      subclass is another learner, never silently labelled as its parent);
    * ``kind``: how it is trained, recorded in metrics.json: ``"fixed"`` (not at all),
      ``"tabular"`` (Q-tables), ``"neural"`` (gradient steps on TorchRL networks) or
      ``"search"`` (policy search on team returns: ``reserve_es``, ``net_es``);
    * ``training_loop``: the runner's loop that trains it (``NUMPY_LOOP``, ``TORCH_LOOP``,
      ``NO_TRAINING`` of ``mrta_rl/loops.py``, or ``"module:function"`` of one's
      own);
    * ``estimate_memory(query)``: a classmethod, given a :class:`MemoryQuery`,
      returning the :class:`~mrta_rl.learners.resources.ResourceEstimate` of its own state
      (tables, networks, buffers) before it is built; the env copies are counted by
      :func:`~mrta_rl.learners.memory.estimate_resources`, which calls it;
    * ``learning_space_dimension(env, partition, settings)``: a classmethod returning the
      analytic learning space dimension (paper eqs. 10-16), or None where there is none.

    Attributes:
        label: Display name in reports.
        kind: How the learner is trained (see above).
        training_loop: ``"module:function"`` of the loop that trains it.
        requires_partition: True if the learner needs the subG partition (paper §4); the runner
            then builds the env with ``Lambda_i = partition.active_tasks(system)``.
        any_team: True if the learned state fits any team (see :meth:`bind_env`).
        hp: The learner's settings, checked, the yaml's defaults filled in (:meth:`__new__`).
        env: The env the learner acts in (built by the runner).
        rng: The learner's only source of randomness.
        partition: The subG partition, or None.
        n_robots: Number of robots ``m``.
        n_actions: Actions per robot, ``K + 1`` (0 = wait, k = bid for slot k).
    """

    label: ClassVar[str]
    kind: ClassVar[LearnerKind]
    training_loop: ClassVar[str]
    requires_partition: ClassVar[bool] = False
    # True if the learned state holds nothing of one team (no robot index, no team size): the
    # learner then trains on a family of teams (:meth:`bind_env`) and a run's state plays any
    # team (``init=<run dir>``)
    any_team: ClassVar[bool] = False
    # True if a training episode is a population of members that play apart (evolution
    # strategies): the numpy loop then spreads them over Ray workers (train.workers). Such a
    # learner has population(), play_members() and record_returns() (learners/search/reserve_es.py)
    population_on_workers: ClassVar[bool] = False
    # True if the torch loop's collection may run on Ray workers (train.workers): a collection
    # policy that reads only the observations (cluster/collection.py)
    collection_on_workers: ClassVar[bool] = False
    facts: ClassVar[tuple[str, ...]] = FACTS  # a base class may require more of its subclasses
    hp: dict[str, Any]  # the checked settings (__new__)

    def __init_subclass__(cls, *, abstract: bool = False, **kwargs: Any) -> None:
        """Refuse a concrete learner class that lacks one of its facts (see the class docstring).

        Args:
            abstract: True for a base class whose subclasses declare the facts.
            **kwargs: Passed on to ``object.__init_subclass__``.

        Raises:
            TypeError: naming the class and the facts it lacks.
        """
        super().__init_subclass__(**kwargs)
        if abstract:
            return
        missing = [] if "label" in cls.__dict__ else ["label"]
        missing += [fact for fact in cls.facts if getattr(cls, fact, None) is None]
        if missing:
            raise TypeError(
                f"learner class {cls.__module__}.{cls.__qualname__} does not declare "
                f"{', '.join(missing)} (see mrta_rl.learners.base.Learner)"
            )

    @classmethod
    def trains(cls) -> bool:
        """True if the learner has a training loop (and so a learned state to save)."""
        return cls.training_loop != NO_TRAINING

    @classmethod
    def base_run(cls, settings: Mapping[str, Any]) -> Path | None:
        """The run dir whose trained learner this learner plays, named by its setting ``base``.

        A learner never loads a run: the runner loads that run's learner (checked to be of the
        run's team, its chain of bases without a loop) and passes it as the runner argument
        ``base_policy``, as it passes ``env``. The default: none.

        Args:
            settings: The learner's settings (a ``learner`` config block).

        Returns:
            The run dir, or None if the settings name none.

        Raises:
            ConfigError: naming ``learner.base`` if its value is neither a run dir nor valid.
        """
        return None

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """The default settings of the class: those of its yaml, their one home.

        The yaml is the file of ``conf/learner/`` whose own ``_target_`` names the class (with
        the learner files it extends); its keys but Hydra's (``_target_``, ``_partial_``,
        ``defaults``) are the settings. A class no shipped yaml names (a plugin built from
        Python) has none: it is given every setting.

        Returns:
            A new dict of the settings (plain yaml values, lists for tuples).

        Raises:
            ConfigError: if two yamls name the class.
        """
        return dict(_yaml_defaults(f"{cls.__module__}.{cls.__qualname__}")[1])

    def __new__(cls, *args: Any, **hyperparameters: Any) -> Learner:
        """Check the hyperparameters against their declarations before ``__init__`` runs.

        The annotations of the keyword-only ``__init__`` arguments are the one declaration of
        each hyperparameter's type and range (``mrta_rl.config``); the runner checks a config
        against them before any work, and this checks a learner built directly in Python.

        The checked settings (the yaml's defaults filled in by :class:`LearnerType`) become the
        learner's :attr:`hp` before ``__init__`` runs: one record of what the learner was built
        with, which its ``save`` writes and its ``load`` compares.

        Raises:
            ConfigError: naming the hyperparameter and what it allows, or the class and the
                settings it was not given and has no default of.
        """
        settings = {k: v for k, v in hyperparameters.items() if k not in RUNNER_ARGUMENTS}
        hp = cls.complete_settings(check_keywords(cls, settings, cls.__name__))
        missing = [name for name in declared_keywords(cls) if name not in hp]
        if missing:
            path = _yaml_defaults(f"{cls.__module__}.{cls.__qualname__}")[0]
            where = f"{path} does not set" if path else "no conf/learner yaml names the class for"
            raise ConfigError(
                f"{cls.__name__}: missing settings {short_list(missing)} ({where} them; pass "
                "them as keywords)"
            )
        learner = super().__new__(cls)
        learner.hp = hp
        return learner

    @classmethod
    def complete_settings(cls, settings: Mapping[str, Any]) -> dict[str, Any]:
        """Settings with the defaults of those they leave out, in the order of the declaration.

        The defaults are the yaml's (:meth:`defaults`); a plugin class may also declare a
        default in its signature, which comes last.

        Args:
            settings: Checked settings (``check_keywords``), maybe partial.

        Returns:
            The declared settings that have a value; those that have none are left out.
        """
        declared = declared_keywords(cls)
        missing = [name for name in declared if name not in settings]
        yaml = cls.defaults() if missing else {}
        filled = check_keywords(cls, {k: yaml[k] for k in missing if k in yaml}, cls.__name__)
        out = {}
        for name, declaration in declared.items():
            if name in settings:
                out[name] = settings[name]
            elif name in filled:
                out[name] = filled[name]
            elif declaration.default is not inspect.Parameter.empty:
                out[name] = declaration.default
        return out

    @classmethod  # noqa: B027 - optional hook, deliberately a no-op
    def check_settings(cls, settings: Mapping[str, Any], team: TrainingTeam) -> None:
        """Refuse settings that contradict each other or the team, before anything is built.

        Each setting's own type and range is its declaration's (checked by ``check_keywords``);
        this checks the relations: between settings (``eps_end <= eps_start``), or between
        settings and the team or the training copies (a batch of whole ticks of every copy). The
        runner calls it before it builds the learner (``validate_config``), and
        :meth:`__init__` calls it for a learner built in Python. Default: nothing to refuse; a
        subclass adds its checks and calls ``super().check_settings``.

        Args:
            settings: The learner's settings, defaults filled in (:meth:`complete_settings`).
            team: What the settings must fit: the team's env, its partition, the copies.

        Raises:
            ConfigError: naming ``learner.<key>`` and what it contradicts.
        """

    def __init__(
        self, *, env: AuctionEnv, rng: np.random.Generator, partition: Partition | None = None
    ) -> None:
        """Keep the env, the generator and the partition.

        Args:
            env: The (training or evaluation) env, built by the runner.
            rng: Generator for every random choice of the learner (exploration, ties).
            partition: The subG partition (paper §4); required if :attr:`requires_partition`.

        Raises:
            ValueError: if the learner requires a partition and none is given.
            ConfigError: on settings that contradict each other or the team
                (:meth:`check_settings`).
        """
        if self.requires_partition and partition is None:
            raise ValueError(f"{type(self).__name__} requires a subG partition (paper §4)")
        type(self).check_settings(self.hp, TrainingTeam(env, partition, env.batch_size))
        self.env = env
        self.rng = rng
        self.partition = partition
        self.n_robots = env.n_robots
        self.n_actions = env.n_actions

    def encode(self, env: AuctionEnv) -> Any:
        """The learner's view of the env's current decision point.

        Called before acting and again after stepping, so the view must not alias arrays that
        :meth:`AuctionEnv.step` changes in place (copy them).

        Args:
            env: The env at a decision point.

        Returns:
            Whatever :meth:`act` and :meth:`update` consume; the default is None (the policy
            needs only the action mask).
        """
        return None

    @abstractmethod
    def act(self, view: Any, mask: np.ndarray, *, explore: bool) -> np.ndarray:
        """Choose one action per robot and copy.

        Args:
            view: Output of :meth:`encode` at this decision point.
            mask: ``[B, m, K + 1]`` bool, valid actions (spec step 4; action 0 always valid).
            explore: True while training (e.g. epsilon-greedy); False for evaluation (greedy).

        Returns:
            ``[B, m]`` int actions, each valid under ``mask``.
        """

    def update(
        self,
        view: Any,
        actions: np.ndarray,
        result: StepResult,
        next_view: Any,
        next_mask: np.ndarray,
    ) -> dict[str, float]:
        """Learn from one tick of every copy (default: no learning).

        Args:
            view: View before acting.
            actions: ``[B, m]`` actions taken.
            result: Team and robot rewards and done flags of the tick.
            next_view: View after the step.
            next_mask: ``[B, m, K + 1]`` valid actions after the step.

        Returns:
            Scalar diagnostics, keys slash-namespaced (``learner/G1/td_error``); may be empty.
        """
        return {}

    @classmethod
    def fits_any_team(cls, settings: Mapping[str, Any]) -> bool:
        """True if a learner of these settings holds nothing of one team (:attr:`any_team`).

        Such a learner trains on a family of teams (:meth:`bind_env`) and its saved state plays
        any team (``init=<run dir>``). Default: the class's :attr:`any_team`; a learner whose
        settings decide it (a network that may or may not read a robot id) overrides this.

        Args:
            settings: The learner's settings (``hp``, or a checked config's).
        """
        return cls.any_team

    @classmethod  # noqa: B027 - optional hook, deliberately a no-op
    def check_family_settings(cls, settings: Mapping[str, Any], horizon: int, copies: int) -> None:
        """Refuse settings that cannot train on a family of teams (one team per episode).

        Default: nothing to refuse.

        Args:
            settings: The learner's settings, defaults filled in.
            horizon: Ticks of an episode.
            copies: Training copies.

        Raises:
            ConfigError: naming the setting.
        """

    def bind_env(self, env: AuctionEnv) -> None:
        """Train on ``env`` from now on: the next team of a family (``system.family``).

        Only a learner that fits any team (:meth:`fits_any_team`) is trained on a family; the
        default refuses.

        Raises:
            NotImplementedError: for a learner tied to one team.
        """
        raise NotImplementedError(f"{type(self).__name__} is trained on one team only")

    def play_on(self, env: AuctionEnv) -> None:
        """Act on the team of ``env`` from now on, without training on it (a planner's base).

        Default: :meth:`bind_env`, for a learner that holds the team it acts on.
        """
        self.bind_env(env)

    def end_episode(self) -> None:  # noqa: B027 - optional hook, deliberately a no-op
        """Advance per-episode schedules (epsilon, learning-rate decay); default: nothing."""

    def learning_space(self) -> dict[str, int]:
        """Learning space dimension (paper eqs. 10-16) and table entries visited.

        Returns:
            ``{"analytic": ..., "visited": ...}`` for learning policies; ``{}`` for fixed ones.
        """
        return {}

    def decision_time(self) -> dict[str, float]:
        """Wall time of the decisions made so far, for a learner whose decisions cost time.

        Evaluation writes it into the ``eval`` block of ``metrics.json`` (``decision_time``).

        Returns:
            ``{"ms_per_tick": ..., "total_s": ..., "ticks": ...}``; ``{}`` (the default) for
            a policy whose decision takes no time worth reporting.
        """
        return {}

    def save(self, directory: Path) -> None:  # noqa: B027 - optional hook, deliberately a no-op
        """Write the learner's state to ``directory`` in safe formats (npz without pickle, json).

        Args:
            directory: Target folder; created by the learner if missing.
        """

    def load(self, directory: Path) -> None:  # noqa: B027 - optional hook, deliberately a no-op
        """Restore the state written by :meth:`save`.

        Args:
            directory: Folder written by :meth:`save`.
        """

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """What training needs beyond :meth:`save` to continue exactly (training checkpoints).

        Called at an episode boundary, after :meth:`save` wrote to ``directory``; subclasses add
        their counters and write further files there (optimizer, ...). The default is the
        generator's state.

        Args:
            directory: The checkpoint folder (holds ``learner/`` written by :meth:`save`).

        Returns:
            JSON-serialisable state, handed back to :meth:`restore_state`.
        """
        return {"rng": self.rng.bit_generator.state}

    def restore_state(self, state: dict[str, Any], directory: Path) -> None:
        """Restore :meth:`checkpoint_state` (after :meth:`load` of the checkpoint's learner state).

        Args:
            state: The dict :meth:`checkpoint_state` returned.
            directory: The checkpoint folder.

        Raises:
            ValueError: if the state does not fit this learner.
        """
        saved = state["rng"]
        if saved.get("bit_generator") != self.rng.bit_generator.state["bit_generator"]:
            raise ValueError(f"generator {saved.get('bit_generator')!r} differs from this run's")
        self.rng.bit_generator.state = saved


class FixedLearner(Learner, abstract=True):
    """Base of the policies that do not learn: no training, no state beyond the env copies.

    The runner evaluates them as they are (:data:`NO_TRAINING`); subclasses declare their
    ``label`` and implement :meth:`Learner.act`.
    """

    kind: ClassVar[LearnerKind] = "fixed"
    training_loop: ClassVar[str] = NO_TRAINING

    @classmethod
    def estimate_memory(cls, query: MemoryQuery) -> ResourceEstimate:
        """Nothing beyond the env copies (counted by ``estimate_resources``)."""
        return ResourceEstimate(cls.__name__)

    @classmethod
    def learning_space_dimension(
        cls, env: AuctionEnv, partition: Partition | None, settings: dict[str, Any]
    ) -> int | None:
        """None: a fixed policy learns nothing."""
        return None


def learner_from_target(target: Any, where: str) -> type[Learner]:
    """The :class:`Learner` class a config's ``_target_`` names, imported.

    Args:
        target: The ``_target_`` value (``mrta_rl.learners.tabular.dql.DQLLearner``).
        where: ``<file or key>`` for messages.

    Returns:
        The class.

    Raises:
        ConfigError: if the name is missing, cannot be imported or is not a Learner.
    """
    from hydra.utils import get_class

    if not isinstance(target, str) or not target:
        raise ConfigError(f"{where}: missing (the learner class)")
    try:
        cls = get_class(target)
    except Exception as err:  # Hydra wraps import errors in several exception types
        raise ConfigError(f"{where}: cannot import learner class {target!r}") from err
    if not (isinstance(cls, type) and issubclass(cls, Learner)):
        raise ConfigError(f"{where}: {target} is not a mrta_rl Learner")
    return cls
