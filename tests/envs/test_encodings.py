"""Tests of the observation encodings (mrta_rl/envs/encodings.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs import encodings as ob
from mrta_rl.systems import RobotSystem, build_system, random_system

ROOT = Path(__file__).resolve().parents[2]


def load_system(name: str) -> RobotSystem:
    return build_system(yaml.safe_load((ROOT / "conf" / "system" / f"{name}.yaml").read_text()))


@pytest.fixture
def quiet_env() -> AuctionEnv:
    """R1: {T1, T3}, R2: {T2}, R3: {T1, T2}; no random arrivals, so tasks are injected by hand."""
    system = RobotSystem.from_table("tiny", {"R1": ["T1", "T3"], "R2": ["T2"], "R3": ["T1", "T2"]})
    return AuctionEnv(system, AuctionParams(arrival_rate=0.0, horizon=50), batch_size=2)


def task(ttype: int, high: int, tid: int, due: int = 0, rnd: int = 1) -> dict[str, int]:
    return dict(type=ttype, high=high, due=due, id=tid, duration=5, round=rnd)


def random_rollout(env: AuctionEnv, ticks: int, seed: int = 0):
    """Yield after each random (valid) joint action."""
    rng = np.random.default_rng(seed)
    for _ in range(ticks):
        logits = rng.random(env.action_mask.shape) * env.action_mask
        env.step(logits.argmax(axis=2))
        yield


def test_hand_built_local_and_group_view(quiet_env):
    env = quiet_env
    # queue order H first, then by id: slot 1 = T1 H, slot 2 = T2 L, slot 3 = T3 L
    env.inject_tasks(0, [task(1, 0, 1), task(0, 1, 0), task(2, 0, 2), task(0, 0, 3)])
    assert env.slot_type[0].tolist() == [0, 1, 2] and env.slot_high[0].tolist() == [1, 0, 0]
    env.last_high_arrival[0] = [-3, -100, -(1 << 30)]  # T1 H three ticks ago (t = 0)
    index = ob.local_state_index(env)
    decode = ob.LocalView(env).decode
    # R1 sees T1 (rank 0) H -> 2, nothing in slot 2, T3 (rank 1) L -> 3; recency over {T1, T3} = 0
    assert decode(0, index[0, 0]) == {"idle": 1, "slots": [2, 0, 3], "battery": 0, "recency": 0}
    # R2 sees only T2 (rank 0) L -> 1 in slot 2; its type's last H was 100 ticks ago -> level 2
    assert decode(1, index[0, 1]) == {"idle": 1, "slots": [0, 1, 0], "battery": 0, "recency": 2}
    # R3 {T1, T2}: T1 H -> 2, T2 L -> 3; recency over {T1, T2} = 0
    assert decode(2, index[0, 2]) == {"idle": 1, "slots": [2, 3, 0], "battery": 0, "recency": 0}
    # explicit mixed radix for R2: radices (2, 3, 3, 3, 2, 3)
    assert index[0, 1] == 1 + 1 * 2 * 3 + 2 * (2 * 27 * 2)
    # group {R1, R2}: T_g = {T1, T2, T3}; codes 1 + 2 rank + high
    group = ob.GroupView(env, [0, 1])
    g_index = ob.group_state_index(env, [0, 1])
    assert group.decode(g_index[0]) == {"slots": [2, 3, 5], "robots": [1, 1], "recency": 0}
    assert ob.group_state_index(env, ["R1", "R2"])[0] == g_index[0]  # ids work as well
    # group {R2}: T_g = {T2}
    assert ob.GroupView(env, [1]).decode(ob.group_state_index(env, [1])[0]) == {
        "slots": [0, 1, 0],
        "robots": [1],
        "recency": 2,
    }


def test_busy_and_battery_levels(quiet_env):
    env = quiet_env
    env.inject_tasks(0, [task(0, 0, 0)])
    # longest duration of R1's types is 12 (H default [6, 12]); threshold 20: low iff battery < 32
    state = env.get_state()
    state["battery"][0] = [31.0, 32.0, 100.0]
    state["busy_until"][0, 2] = 5
    env.set_state(state)  # and its slots and masks
    assert ob.battery_level(env)[0].tolist() == [1, 0, 0]
    index = ob.local_state_index(env)
    decode = ob.LocalView(env).decode
    assert decode(0, index[0, 0])["battery"] == 1
    assert decode(2, index[0, 2])["idle"] == 0
    # group states: 0 busy, 1 idle ok, 2 idle low
    group = ob.GroupView(env, [0, 1, 2])
    assert group.decode(ob.group_state_index(env, [0, 1, 2])[0])["robots"] == [2, 1, 0]
    # the other copy is untouched
    assert ob.battery_level(env)[1].tolist() == [0, 0, 0]


@pytest.mark.parametrize(("ago", "level"), [(0, 0), (3, 0), (4, 1), (10, 1), (11, 2), (None, 2)])
def test_recency_thresholds(quiet_env, ago, level):
    env = quiet_env
    env.t[:] = 20
    env.last_high_arrival[0, 0] = -(1 << 30) if ago is None else 20 - ago  # T1 only
    assert ob.recency_level(env, np.array([True, False, False]))[0] == level
    per_robot = ob.recency_level(env, env.active_tasks)  # R1 has T1, R2 does not
    assert per_robot.shape == (2, 3) and per_robot[0, 0] == level and per_robot[0, 1] == 2


def test_recency_takes_latest_type(quiet_env):
    env = quiet_env
    env.t[:] = 30
    env.last_high_arrival[0] = [5, 25, 29]
    assert ob.recency_level(env, np.array([True, True, False]))[0] == 1
    assert ob.recency_level(env, np.array([True, True, True]))[0] == 0
    with pytest.raises(ValueError, match="types_mask"):
        ob.recency_level(env, np.ones(4, bool))


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_counts_match_formula(name):
    env = AuctionEnv(load_system(name))
    K = env.n_slots
    lam = env.active_tasks.sum(axis=1)
    assert ob.local_state_count(env) == [2 * (1 + 2 * int(x)) ** K * 2 * 3 for x in lam]
    m, n = env.n_robots, env.n_task_types
    assert ob.group_state_count(env, list(range(m))) == (1 + 2 * n) ** K * 3**m * 3


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_indices_in_range_and_decode_to_env_fields(name):
    """Decoding recovers the env's fields, so distinct states get distinct indices."""
    env = AuctionEnv(load_system(name), AuctionParams(horizon=200), batch_size=16, seed=3)
    view = ob.LocalView(env)
    groups = [[0, 1], list(range(env.n_robots))]
    gviews = [ob.GroupView(env, g) for g in groups]
    counts = np.array(ob.local_state_count(env))
    seen: dict[int, tuple] = {}
    for _ in random_rollout(env, 60):
        index = ob.local_state_index(env)
        assert index.dtype == np.int64 and (index >= 0).all() and (index < counts).all()
        battery, active = ob.battery_level(env), env.active_tasks
        recency = ob.recency_level(env, active)
        for b in range(0, 16, 5):
            for i in range(env.n_robots):
                fields = view.decode(i, index[b, i])
                assert fields["idle"] == env.idle[b, i]
                assert fields["battery"] == battery[b, i] and fields["recency"] == recency[b, i]
                for k, code in enumerate(fields["slots"]):
                    ttype = env.slot_type[b, k]
                    if ttype < 0 or not active[i, ttype]:
                        assert code == 0
                    else:
                        rank = int(active[i, :ttype].sum())
                        assert code == 1 + 2 * rank + env.slot_high[b, k]
        for g, gview in zip(groups, gviews, strict=True):
            g_index = ob.group_state_index(env, g)
            assert ((g_index >= 0) & (g_index < gview.count)).all()
            for b in range(16):
                key = (tuple(g), int(g_index[b]))
                state = (
                    tuple(env.slot_type[b]),
                    tuple(env.slot_high[b]),
                    tuple(env.idle[b, g]),
                    tuple(battery[b, g] * env.idle[b, g]),
                    int(ob.recency_level(env, gview.types_mask)[b]),
                )
                if len(g) == env.n_robots:  # whole system: every slot type is in T_g
                    assert seen.setdefault(key, state) == state  # same index -> same state


def test_group_overflow_is_a_clear_error():
    env = AuctionEnv(random_system(60, 6, 0.5, 0))
    count = ob.group_state_count(env, list(range(60)))
    assert count == (1 + 2 * 6) ** 3 * 3**60 * 3  # exact Python int
    with pytest.raises(OverflowError, match="2\\*\\*63"):
        ob.group_state_index(env, list(range(60)))
    with pytest.raises(ValueError):
        ob.GroupView(env, [])


@pytest.fixture
def played_env() -> AuctionEnv:
    """System-II, 8 copies, after 20 ticks of random valid actions."""
    env = AuctionEnv(load_system("system2"), batch_size=8, seed=1)
    for _ in random_rollout(env, 20):
        pass
    return env


def test_features_are_one_hot(played_env):
    env = played_env
    m, n, K = env.n_robots, env.n_task_types, env.n_slots
    local = ob.local_features(env)
    assert local.shape == (8, m, ob.local_feature_size(env)) and local.dtype == np.float32
    c = 1 + 2 * n
    slots = local[..., 1 : 1 + K * c].reshape(8, m, K, c)
    assert (slots.sum(-1) == 1).all()
    np.testing.assert_array_equal(local[..., 0], env.idle)
    base = 1 + K * c
    np.testing.assert_array_equal(local[..., base], ob.battery_level(env))
    np.testing.assert_array_equal(
        local[..., base + 1 : base + 4].argmax(-1), ob.recency_level(env, env.active_tasks)
    )
    np.testing.assert_array_equal(local[..., base + 4 :], np.broadcast_to(np.eye(m), (8, m, m)))
    # a robot's slot one-hot is nonzero only for types in Lambda_i
    codes = slots.argmax(-1)  # [B, m, K]
    visible = codes > 0
    types = (codes - 1) // 2
    assert env.active_tasks[np.arange(m)[None, :, None], types][visible].all()
    glob = ob.global_features(env)
    assert glob.shape == (8, ob.global_feature_size(env)) and glob.dtype == np.float32
    g_slots = glob[:, : K * c].reshape(8, K, c)
    assert (g_slots.sum(-1) == 1).all()
    expected = np.where(env.slot_type >= 0, 1 + 2 * env.slot_type + env.slot_high, 0)
    np.testing.assert_array_equal(g_slots.argmax(-1), expected)
    rec = glob[:, K * c + 2 * m :].reshape(8, n, 3)
    assert (rec.sum(-1) == 1).all()


def test_time_to_free_by_hand(quiet_env):
    """Free levels, queue levels and the digits they add to the local and group views."""
    env = quiet_env
    # queue: T1 H, T2 L, T3 L, T1 L, T2 L (5 tasks); slots 1-3 = T1 H, T2 L, T3 L
    tasks = [task(1, 0, 1), task(0, 1, 0), task(2, 0, 2), task(0, 0, 3), task(1, 0, 4)]
    env.inject_tasks(0, tasks)
    state = env.get_state()
    state["busy_until"][0] = [-1, 2, 9]  # t = 0: R1 idle, R2 idle again at tick 3, R3 at tick 10
    env.set_state(state)  # and its slots and masks
    assert ob.free_level(env)[0].tolist() == [0, 1, 2]  # FREE_SOON = 3: 3 ticks is soon
    counts = ob.queue_counts(env)[0]  # [n, 2], index 0 = L
    assert counts.tolist() == [[1, 1], [2, 0], [1, 0]]
    # over Lambda_i: R1 {T1, T3}: H 1 -> 1, L 2 -> 0; R2 {T2}: H 0, L 2 -> 0;
    # R3 {T1, T2}: H 1 -> 1, L 3 -> 1 (L thresholds 2, 8)
    assert ob.queue_level(env, env.active_tasks)[0].tolist() == [[1, 0], [0, 0], [1, 1]]
    assert ob.queue_level(env, np.ones(3, bool))[0].tolist() == [1, 1]  # L 4 > 2 -> level 1
    view = ob.LocalView(env, "time_to_free")
    index = ob.local_state_index(env, "time_to_free")
    paper = ob.LocalView(env).decode(0, ob.local_state_index(env)[0, 0])
    assert paper.pop("idle") == 1
    fields = view.decode(0, index[0, 0])
    assert fields == {"free": 0, **paper, "queue_high": 1, "queue_low": 0}
    assert view.decode(2, index[0, 2])["free"] == 2 and view.decode(1, index[0, 1])["free"] == 1
    group = ob.GroupView(env, [0, 1, 2], "time_to_free")
    g_fields = group.decode(ob.group_state_index(env, [0, 1, 2], "time_to_free")[0])
    # robot states: 1 idle ok, 3 busy but free soon, 0 busy for longer
    assert g_fields["robots"] == [1, 3, 0]
    assert (g_fields["queue_high"], g_fields["queue_low"]) == (1, 1)
    with pytest.raises(ValueError, match="features must be one of"):
        ob.local_state_index(env, "nope")


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_time_to_free_counts_and_indices(name):
    env = AuctionEnv(load_system(name), AuctionParams(horizon=200), batch_size=16, seed=3)
    K, m, n = env.n_slots, env.n_robots, env.n_task_types
    lam = env.active_tasks.sum(axis=1)
    counts = ob.local_state_count(env, "time_to_free")
    assert counts == [3 * (1 + 2 * int(x)) ** K * 2 * 3 * 9 for x in lam]
    team = list(range(m))
    assert ob.group_state_count(env, team, "time_to_free") == (1 + 2 * n) ** K * 4**m * 3 * 9
    local, group = ob.LocalView(env, "time_to_free"), ob.GroupView(env, team, "time_to_free")
    paper_local, paper_group = ob.LocalView(env), ob.GroupView(env, team)
    for _ in random_rollout(env, 40):
        index = ob.local_state_index(env, "time_to_free")
        assert (index >= 0).all() and (index < np.array(counts)).all()
        free, queue = ob.free_level(env), ob.queue_level(env, env.active_tasks)
        g_index = ob.group_state_index(env, team, "time_to_free")
        g_paper = ob.group_state_index(env, team)
        for b in range(0, 16, 3):
            for i in range(m):
                got = local.decode(i, index[b, i])
                want = paper_local.decode(i, ob.local_state_index(env)[b, i])
                assert got.pop("free") == free[b, i] and want.pop("idle") == env.idle[b, i]
                assert got == {**want, "queue_high": queue[b, i, 0], "queue_low": queue[b, i, 1]}
            got, want = group.decode(g_index[b]), paper_group.decode(g_paper[b])
            assert got["slots"] == want["slots"] and got["recency"] == want["recency"]
            assert [r % 3 if r < 3 else 0 for r in got["robots"]] == want["robots"]
            assert [r == 3 for r in got["robots"]] == (free[b] == 1).tolist()


def test_time_to_free_neural_features(played_env):
    env = played_env
    m, n, K = env.n_robots, env.n_task_types, env.n_slots
    paper = ob.local_features(env)
    local = ob.local_features(env, "time_to_free")
    assert local.shape == (8, m, ob.local_feature_size(env, "time_to_free"))
    assert local.shape[-1] == paper.shape[-1] + 9
    at = ob.local_feature_layout(K, n, "time_to_free")
    np.testing.assert_array_equal(local[..., : at["free"].start], paper[..., : at["free"].start])
    np.testing.assert_array_equal(local[..., at["robot"]], paper[..., -m:])
    np.testing.assert_array_equal(local[..., at["free"]].argmax(-1), ob.free_level(env))
    q = local[..., at["queue"]].reshape(8, m, 2, 3)
    assert (q.sum(-1) == 1).all()
    np.testing.assert_array_equal(q.argmax(-1), ob.queue_level(env, env.active_tasks))
    glob = ob.global_features(env, "time_to_free")
    base = ob.global_feature_size(env)
    assert glob.shape == (8, base + 3 * m + 6 * n)
    np.testing.assert_array_equal(glob[:, :base], ob.global_features(env))
    free = glob[:, base : base + 3 * m].reshape(8, m, 3)
    np.testing.assert_array_equal(free.argmax(-1), ob.free_level(env))
    queue = glob[:, base + 3 * m :].reshape(8, n, 2, 3)
    np.testing.assert_array_equal(queue.argmax(-1), ob.queue_level(env, np.eye(n, dtype=bool)))


def named(row: np.ndarray, names: tuple[str, ...]) -> dict[str, float]:
    return {name: round(float(v), 6) for name, v in zip(names, row, strict=True)}


def test_set_inputs_hand_checked(quiet_env):
    env = quiet_env
    # slots: T1 H, T2 L in its second round, T3 L; T1 L (id 3) stays queued behind them
    env.inject_tasks(0, [task(0, 1, 0), task(1, 0, 1, rnd=2), task(2, 0, 2), task(0, 0, 3)])
    state = env.get_state()
    state["battery"][0, 0] = 50.0
    state["busy_until"][0, 2] = 1  # R3 idle again at tick 2: "free soon"
    state["last_high_arrival"][0] = [-3, -100, -(1 << 30)]  # a T1 H three ticks ago (t = 0)
    env.set_state(state)
    x = ob.set_inputs(env)
    assert x.robots.shape == (2, 3, ob.ROBOT_TOKEN_SIZE) and x.robots.dtype == np.float32
    assert x.slots.shape == (2, 3, ob.SLOT_TOKEN_SIZE)
    assert x.types.shape == (2, 3, ob.TYPE_TOKEN_SIZE)
    np.testing.assert_array_equal(x.robot_types[1], env.active_tasks)
    r1, r2, r3 = (named(x.robots[0, i], ob.ROBOT_FEATURES) for i in range(3))
    # R1 {T1, T3}: idle, battery 50/100 (low below 20 + 12), T1 H 3 ticks ago: recency 0;
    # queued over its types: 1 H (level 1), 2 L (level 0); no other idle robot for T1 or T3,
    # and none idle or free soon for T3
    assert r1 == {
        "idle": 1, "free_soon": 0, "time_to_free": 0, "battery": 0.5, "battery_low": 0,
        "recency_0": 1, "recency_1": 0, "recency_2": 0,
        "queued_high": 0.25, "queued_low": 0.125, "queue_level_high": 0.5, "queue_level_low": 0,
        "sole_idle": 1, "others_idle": 0, "others_soon": 0, "versatility": round(2 / 3, 6),
    }  # fmt: skip
    # R2 {T2}: no H of T2 for 100 ticks (recency 2), 1 L queued; R3 is free soon for T2
    assert r2 == {
        "idle": 1, "free_soon": 0, "time_to_free": 0, "battery": 1, "battery_low": 0,
        "recency_0": 0, "recency_1": 0, "recency_2": 1,
        "queued_high": 0, "queued_low": 0.0625, "queue_level_high": 0, "queue_level_low": 0,
        "sole_idle": 1, "others_idle": 0, "others_soon": 0.25, "versatility": round(1 / 3, 6),
    }  # fmt: skip
    # R3 {T1, T2}: busy until tick 1, idle in 2 ticks; R1 idle for T1, R2 for T2
    assert r3 == {
        "idle": 0, "free_soon": 1, "time_to_free": round(2 / 24, 6), "battery": 1,
        "battery_low": 0, "recency_0": 1, "recency_1": 0, "recency_2": 0,
        "queued_high": 0.25, "queued_low": 0.125, "queue_level_high": 0.5, "queue_level_low": 0,
        "sole_idle": 0, "others_idle": 0.25, "others_soon": 0.25, "versatility": round(2 / 3, 6),
    }  # fmt: skip
    slots = [named(x.slots[0, k], ob.SLOT_FEATURES) for k in range(3)]
    same = {"present": 1, "waiting": 0, "duration": round(5 / 24, 6), "bidders": 0.25}
    assert slots == [
        {**same, "high": 1, "round_2": 0},
        {**same, "high": 0, "round_2": 1},
        {**same, "high": 0, "round_2": 0},
    ]
    assert x.slot_type[0].tolist() == [0, 1, 2]
    t1, t2, t3 = (named(x.types[0, j], ob.TYPE_FEATURES) for j in range(3))
    assert t1 == {
        "queued_high": 0.25, "queued_low": 0.0625, "queue_level_high": 0.5, "queue_level_low": 0,
        "recency_0": 1, "recency_1": 0, "recency_2": 0, "since_high": 0.125,
        "idle_robots": 0.25, "soon_robots": 0.5, "robots": 0.25,
    }  # fmt: skip
    assert t2["recency_2"] == 1 and t2["since_high"] == 1 and t2["soon_robots"] == 0.5
    assert t3["since_high"] == 1 and t3["soon_robots"] == 0.25 and t3["robots"] == 0.125
    # copy 1 has no task: empty slots are all zeros, type 0
    assert not x.slots[1].any() and x.slot_type[1].tolist() == [0, 0, 0]


def test_set_inputs_widths_do_not_depend_on_the_team():
    widths = set()
    for system in (load_system("system1"), load_system("system2"), random_system(60, 12, seed=1)):
        env = AuctionEnv(system, AuctionParams(horizon=50), batch_size=2)
        for _ in random_rollout(env, 40):
            x = ob.set_inputs(env)
            assert all(((a >= 0) & (a <= 1)).all() for a in (x.robots, x.slots, x.types))
            # the levels agree with the coarse encodings' own helpers
            at = {name: k for k, name in enumerate(ob.ROBOT_FEATURES)}
            levels = ob.queue_level(env, env.active_tasks)  # [B, m, 2]: H, L
            np.testing.assert_array_equal(x.robots[..., at["queue_level_high"]], levels[..., 0] / 2)
            np.testing.assert_array_equal(x.robots[..., at["queue_level_low"]], levels[..., 1] / 2)
            recency = x.robots[..., at["recency_0"] : at["recency_2"] + 1].argmax(-1)
            np.testing.assert_array_equal(recency, ob.recency_level(env, env.active_tasks))
        widths.add((x.robots.shape[-1], x.slots.shape[-1], x.types.shape[-1]))
    assert widths == {(ob.ROBOT_TOKEN_SIZE, ob.SLOT_TOKEN_SIZE, ob.TYPE_TOKEN_SIZE)}


def test_zones_hide_other_zones_slots_from_local_features_and_bidders():
    # four robots of one type in 2 zones: R1, R2 bid for slot 1, R3, R4 for slot 2; R2 is busy
    robots = {f"R{i}": ["T1"] for i in range(1, 5)}
    system = build_system({"name": "zoned", "robots": robots})
    env = AuctionEnv(system, AuctionParams(arrival_rate=0.0, slots=2, zones=2))
    env.busy_until[0, 1] = 5
    env.inject_tasks(0, [task(0, 0, 0), task(0, 0, 1)])  # two T1 L tasks, in slots 1 and 2
    bidders = ob.set_inputs(env).slots[0, :, ob.SLOT_FEATURES.index("bidders")]
    assert bidders.tolist() == [1 / 4, 2 / 4]  # R1 for slot 1; R3 and R4 for slot 2
    at = ob.local_feature_layout(2, 1, "paper")
    codes = ob.local_features(env)[0][:, at["slots"]].reshape(4, 2, 3).argmax(-1)  # [m, K]
    # code 1 = a T1 L task the robot may bid for, 0 = none (another zone's slot)
    assert codes.tolist() == [[1, 0], [1, 0], [0, 1], [0, 1]]
