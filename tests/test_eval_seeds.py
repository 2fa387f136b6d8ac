"""Seed families of the benchmark: fixed codes, disjoint by construction, apart from every legacy seed."""

import numpy as np
import pytest

from pivla.envs.rollout import episode_seed
from pivla.envs.seeds import (
    BASE,
    CONDITIONS,
    FAMILIES,
    MAX_CONDITIONS,
    MAX_EPISODES,
    MAX_FAMILIES,
    MAX_TASKS,
    TASKS,
    SeedKey,
    check_disjoint,
    decode,
    family_of,
    family_seeds,
    legacy_test_seed,
    require_family,
    seed_for,
    seeds_for,
)
from pivla.envs.tabletop import make_env, tasks
from pivla.evaluation.runner import job_seed


def test_every_twin_task_and_condition_has_its_own_code():
    from pivla.envs.so101 import tasks as so101_tasks

    names = [t.name for suite in tasks.SUITES.values() for t in suite]
    so101 = [t.name for suite in so101_tasks.SUITES.values() for t in suite]
    assert not set(names) & set(so101)  # one code per name: the two twins never share a task name
    assert set(names) | set(so101) == set(TASKS)
    for table, limit in ((TASKS, MAX_TASKS), (CONDITIONS, MAX_CONDITIONS)):
        codes = list(table.values())
        assert len(set(codes)) == len(codes) and 0 <= min(codes) and max(codes) < limit
    assert len(FAMILIES) == len(set(FAMILIES)) <= MAX_FAMILIES
    assert FAMILIES[:3] == ("train", "validation", "test")


@pytest.mark.parametrize("condition", list(CONDITIONS))
def test_train_validation_test_and_holdout_are_disjoint_for_every_condition(condition):
    by_family = {f: family_seeds(f, [condition], episodes=2000) for f in FAMILIES}
    sizes = check_disjoint(by_family)
    assert sizes == dict.fromkeys(FAMILIES, 2000 * len(TASKS))  # no two keys of a family share a seed either
    for values in by_family.values():
        assert values.min() >= BASE and values.max() < 2 * BASE


def test_families_are_disjoint_across_all_conditions():
    everything = {f: family_seeds(f, episodes=4096) for f in FAMILIES}
    assert sum(check_disjoint(everything).values()) == len(FAMILIES) * len(CONDITIONS) * len(TASKS) * 4096
    last = [seed_for(f, c, t, MAX_EPISODES - 1) for f in FAMILIES for c in CONDITIONS for t in TASKS]
    assert len(set(last)) == len(last) and max(last) < 2 * BASE  # the top of the episode range stays in its field


def test_no_family_meets_a_legacy_seed():
    """Seeds used before the families (pivla demo's: training demos from seed 0, validation demos from seed 1,
    validation rollouts at seed 1, tests at seed 1000) are 31-bit, the families start at 2**31."""
    legacy = {
        "train_demos": [episode_seed(episode_seed(0, t), a) for t in range(len(TASKS)) for a in range(300)],
        "validation_demos": [episode_seed(episode_seed(1, t), a) for t in range(len(TASKS)) for a in range(50)],
        "validation_rollouts": [job_seed(1, t, e) for t in range(len(TASKS)) for e in range(50)],
        "legacy_test": [legacy_test_seed(t, e) for t in range(len(TASKS)) for e in range(200)],
    }
    assert all(max(v) < BASE for v in legacy.values())
    assert all(family_of(s) == "legacy" and decode(s) is None for s in legacy["legacy_test"][:50])
    check_disjoint({f: family_seeds(f, episodes=300) for f in FAMILIES} | legacy)
    assert legacy_test_seed(3, 7) == job_seed(1000, 3, 7)
    assert check_disjoint({"none": [], "one": [1], "twice": [2, 2]}) == {"none": 0, "one": 1, "twice": 1}
    with pytest.raises(ValueError, match="'validation' and 'test' share 1 seeds"):
        check_disjoint({"validation": [5, 6], "test": [6, 7]})


def test_seeds_decode_back_to_their_key():
    rng = np.random.default_rng(0)
    for _ in range(200):
        key = SeedKey(FAMILIES[rng.integers(len(FAMILIES))], list(CONDITIONS)[rng.integers(len(CONDITIONS))],
                      list(TASKS)[rng.integers(len(TASKS))], int(rng.integers(MAX_EPISODES)))
        value = seed_for(key.family, key.condition, key.task, key.episode)
        assert decode(value) == key and family_of(value) == key.family
    assert seeds_for("test", "unseen_env", "ball_left", 3) == [seed_for("test", "unseen_env", "ball_left", e)
                                                              for e in range(3)]
    assert seeds_for("test", "push_arm", "rock_left", [4, 9])[1] == seed_for("test", "push_arm", "rock_left", 9)
    for bad, msg in ((("exam", "in_distribution", "block_left", 0), "seed family"),
                     (("test", "fog", "block_left", 0), "condition"),
                     (("test", "in_distribution", "juggle", 0), "task"),
                     (("test", "in_distribution", "block_left", MAX_EPISODES), "episode")):
        with pytest.raises(ValueError, match=msg):
            seed_for(*bad)
    with pytest.raises(ValueError, match="unassigned"):
        decode(BASE + (MAX_CONDITIONS - 1 << 22))
    with pytest.raises(ValueError, match="not an episode seed"):
        decode(2 * BASE)


def test_require_family_refuses_episodes_of_other_families():
    val = seeds_for("validation", "in_distribution", "block_left", 5)
    require_family(val, {"validation"}, "calibration episodes")
    require_family(val + [legacy_test_seed(0, 0)], {"validation", "legacy"}, "calibration episodes")
    with pytest.raises(ValueError, match=r"calibration episodes: 2 episode seeds .*\(test\)"):
        require_family(val + seeds_for("test", "in_distribution", "block_left", 2), {"validation"},
                       "calibration episodes")


def test_the_twin_plays_family_seeds_deterministically():
    env = make_env("pick_place", "ball_left", render=False)
    first, second = seeds_for("holdout", "in_distribution", "ball_left", 2)  # neighbouring integers
    a = env.reset(seed=first)[0]["ee_pos"], env.privileged_state()["objects"]["ball"]["pos"].copy()
    b = env.reset(seed=second)[0]["ee_pos"], env.privileged_state()["objects"]["ball"]["pos"].copy()
    again = env.reset(seed=first)[0]["ee_pos"], env.privileged_state()["objects"]["ball"]["pos"].copy()
    assert np.array_equal(a[0], again[0]) and np.array_equal(a[1], again[1])
    assert np.linalg.norm(a[1] - b[1]) > 1e-3
