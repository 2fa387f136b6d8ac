"""Latency-aware execution: the latency model, sync and async modes on a scripted policy whose chunks are known
exactly, the faults (stale, out-of-order, a lost link), zero latency against today's loop on the twin, and the
evaluation's new outputs."""

import dataclasses
import json

import numpy as np
import pytest

from pivla.control import make_executor, run_episode
from pivla.control.asynchronous import AsyncConfig, SyncConfig
from pivla.control.executors import executor_config
from pivla.control.latency import (
    Arrival,
    Latency,
    SimulatedLink,
    delay_steps,
    latency_rng,
    parse_latency,
)
from tests.test_control_executors import ScriptedPolicy


class CountingEnv:
    """Observations {"t": step} at 10 Hz, never done before ``max_steps``: the executor alone decides the actions."""

    control_hz = 10

    def __init__(self, max_steps=14):
        self.max_steps, self.unwrapped = max_steps, self

    def reset(self, seed=None, options=None):
        self.t = 0
        return {"t": 0}, {}

    def step(self, action):
        self.t += 1
        return {"t": self.t}, 0.0, False, False, {}


def played(result):
    """(chunk, plan step) of every commanded action, "." for a hold (no end-effector motion)."""
    return [(int(a[0]), int(a[1])) if a[:6].any() else "." for a in result.actions]


def episode(executor="fixed", execution=None, latency="0", policy=None, steps=14, seed=1, **options):
    policy = policy or ScriptedPolicy()
    return run_episode(CountingEnv(steps), policy, make_executor(executor, **options), seed=seed,
                       execution=execution, latency=latency)


# -- the latency model ------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, problem", [
    ("abc", "expected MEAN"), ("-5", ">= 0"), ("nan", "finite"), ("inf:1", "finite"), ("10:-1", ">= 0"),
    ("1:2:3", "expected MEAN"), ("0:10", "jitter needs a mean"), ("", "expected MEAN")])
def test_bad_latency_is_named(text, problem):
    with pytest.raises(ValueError, match=problem):
        parse_latency(text)


def test_latency_parses_and_draws_from_the_seed():
    assert parse_latency("100") == Latency(100.0, 0.0) and parse_latency(" 100:20 ") == Latency(100.0, 20.0)
    assert parse_latency("real").real and parse_latency("0").zero
    with pytest.raises(ValueError, match="or 'real'"):
        parse_latency("soon")
    with pytest.raises(ValueError):
        parse_latency("real", allow_real=False)
    lat = Latency(200.0, 50.0)
    first, again, other = latency_rng(3), latency_rng(3), latency_rng(4)
    draws = [lat.draw_ms(first) for _ in range(5)]
    assert draws == [lat.draw_ms(again) for _ in range(5)] != [lat.draw_ms(other) for _ in range(5)]
    rng = latency_rng(0)
    many = [lat.draw_ms(rng) for _ in range(20000)]
    assert np.mean(many) == pytest.approx(200, rel=0.02) and np.std(many) == pytest.approx(50, rel=0.05)
    assert min(many) > 0
    assert [delay_steps(ms, 10) for ms in (0, 1, 100, 100.5, 300)] == [0, 1, 1, 2, 3]


# -- sync and async on a scripted policy --------------------------------------------------------------------
def test_zero_latency_sync_is_the_executors_own_loop():
    for name, options in (("fixed", {"horizon": 3}), ("aurd", {}), ("ensemble", {}), ("adahorizon", {})):
        a = episode(name, policy=ScriptedPolicy(latent_error={2: 2.0, 3: 2.0}), **options)
        b = episode(name, SyncConfig(), "0", policy=ScriptedPolicy(latent_error={2: 2.0, 3: 2.0}), **options)
        assert np.array_equal(a.actions, b.actions) and a.trace == b.trace and a.plans == b.plans, name


def test_sync_latency_holds_pose_then_starts_the_chunk_at_its_first_action():
    r = episode("fixed", SyncConfig(), "200", horizon=3)  # 200 ms at 10 Hz: every chunk 2 steps late
    assert played(r) == [".", ".", (1, 0), (1, 1), (1, 2), ".", ".", (2, 0), (2, 1), (2, 2), ".", ".", (3, 0), (3, 1)]
    assert [row["t"] for row in r.trace] == list(range(14)) and sum(row.get("idle", False) for row in r.trace) == 6
    s = r.summary()
    assert s["idle_steps"] == 6 and s["delay_steps_mean"] == 2.0 and s["steps_to_success"] is None
    assert s["queries_per_minute"] == pytest.approx(3 / (14 / 10 / 60))
    assert r.actions[1][6] == -1.0 and r.actions[5][6] == 1.0  # a hold keeps the gripper as it was


def test_async_skips_the_actions_that_passed_and_sends_at_the_threshold():
    r = episode("fixed", AsyncConfig(threshold=2), "200", horizon=3)
    # sent at t=0, usable at t=2: plan steps 2-4; the next sent at t=3 (2 left) arrives as the plan completes
    assert played(r) == [".", ".", (1, 2), (1, 3), (1, 4), (2, 2), (2, 3), (2, 4), (3, 2), (3, 3), (3, 4),
                         (4, 2), (4, 3), (4, 4)]
    sent = [row["t"] for row in r.trace if "sent" in row]
    assert sent == [0, 3, 6, 9, 12] and r.summary()["idle_steps"] == 2
    assert [row.get("offset") for row in r.trace if row.get("replanned")] == [2, 2, 2, 2]


@pytest.mark.parametrize("name", ["fixed", "adahorizon", "ensemble"])
def test_async_at_zero_latency_and_threshold_0_plays_the_sync_episode(name):
    options = {"horizon": 3} if name == "fixed" else {}
    u_act = [0, 0, 0.01, 0.02, 0.05, 0.07, 0.01, 0]  # AdaHorizon's horizons vary
    a = episode(name, SyncConfig(), "0", policy=ScriptedPolicy(u_act=u_act), **options)
    b = episode(name, AsyncConfig(threshold=0), "0", policy=ScriptedPolicy(u_act=u_act), **options)
    assert np.array_equal(a.actions, b.actions) and a.queries == b.queries


def test_async_blend_mixes_the_old_chunks_actions_into_the_seam():
    switch = episode("fixed", AsyncConfig(threshold=4), "100", horizon=5, steps=6)
    blend = episode("fixed", AsyncConfig(threshold=4, seam="blend", blend_steps=2), "100", horizon=5, steps=6)
    # chunk 1 starts at t=1 (plan steps 1-5); with 4 left at t=2 chunk 2 is sent, and takes over at t=3 at its step 1
    assert played(switch) == [".", (1, 1), (1, 2), (2, 1), (2, 2), (3, 1)]
    def mix(w, old, new):
        return (1 - w) * np.array(old, float) + w * np.array(new, float)

    # (chunk, step) of the first two dims; chunk 1 still had its steps 3 and 4 for t = 3, 4
    assert blend.actions[3][:2] == pytest.approx(mix(1 / 3, [1, 3], [2, 1]))
    assert blend.actions[4][:2] == pytest.approx(mix(2 / 3, [1, 4], [2, 2]))
    assert blend.actions[5][:2] == pytest.approx(mix(1 / 3, [2, 3], [3, 1]))
    assert np.array_equal(blend.actions[:3], switch.actions[:3]) and blend.actions[3][6] == switch.actions[3][6]


def test_async_align_makes_up_the_motion_the_new_chunk_planned_for_the_skipped_steps():
    switch = episode("fixed", AsyncConfig(threshold=2, seam="switch"), "200", horizon=3, steps=8)
    align = episode("fixed", AsyncConfig(threshold=2, seam="align"), "200", horizon=3, steps=8)  # over 2 steps
    a, b = align.actions[:, :2], switch.actions[:, :2]  # chunk c's motion at its step k is (c, k)
    # chunk 1 (sent at t=0) starts at t=2 at its step 2; the arm held over t=0, 1, where it planned (1, 0) + (1, 1)
    assert np.allclose(a[2:4], b[2:4] + (np.array([1, 0]) + np.array([1, 1])) / 2)
    # chunk 2 (sent at t=3) takes over at t=5 at its step 2; over t=3, 4 the arm did a[3] + a[4]
    missing = np.array([2, 0]) + np.array([2, 1]) - a[3] - a[4]
    assert np.allclose(a[5:7], b[5:7] + missing / 2) and np.allclose(a[4], b[4]) and np.allclose(a[7], b[7])
    # so from each chunk's observation on, the arm travels the path that chunk planned
    assert np.allclose(a[3:7].sum(0), sum(np.array([2, k]) for k in range(4)))
    assert np.allclose(a[0:4].sum(0), sum(np.array([1, k]) for k in range(4)))
    assert np.array_equal(align.actions[:, 6], switch.actions[:, 6])  # the gripper is the chunk's
    zero = [episode("fixed", AsyncConfig(seam=seam), "0", horizon=3) for seam in ("align", "switch")]
    assert np.array_equal(zero[0].actions, zero[1].actions)  # at 0 ms nothing is skipped


def test_async_aurd_sends_on_a_cut_and_drops_the_rest_when_the_chunk_arrives():
    # the observation at t=2 deviates from chunk 1's prediction (U = 0.6 > tau_high): a query goes out at t=2
    # and its chunk replaces chunk 1 the moment it arrives; a chunk sent on the threshold waits for the plan
    r = episode("aurd", AsyncConfig(threshold=3), "100", policy=ScriptedPolicy(latent_error={2: 2.0}))
    assert played(r) == [".", (1, 1), (1, 2), (2, 1), (2, 2), (2, 3), (2, 4), (2, 5), (3, 3), (3, 4), (3, 5),
                         (3, 6), (3, 7), (4, 3)]
    assert r.plans[0] == (2, "replan") and r.plans[1] == (5, "complete")
    cut = next(row for row in r.trace if row.get("cut"))
    assert cut["t"] == 2 and cut["sent"] == "replan" and cut["cut_u"] == pytest.approx(0.6)
    assert r.trace[3]["committed"] and r.trace[3]["ended"] == "replan"
    assert [row["t"] for row in r.trace if row.get("sent") == "threshold"] == [0, 5, 10]


def test_async_aurd_at_zero_latency_executes_no_untrusted_step():
    r = episode("aurd", AsyncConfig(threshold=0), "0", policy=ScriptedPolicy(latent_error={2: 2.0}))
    assert played(r)[:4] == [(1, 0), (1, 1), (2, 0), (2, 1)] and r.plans[0] == (2, "replan")


def test_async_aurd_refuses_the_after_check():
    with pytest.raises(ValueError, match="check='before'"):
        episode("aurd", AsyncConfig(), "100", check="after")


def same_decisions(sync, asynchronous):
    """The async episode made every decision of the sync one: actions, plan log, queries, and every field of each
    sync trace row (async rows add their own: chunk, sent, offset, cut)."""
    assert np.array_equal(sync.actions, asynchronous.actions)
    assert sync.plans == asynchronous.plans and sync.queries == asynchronous.queries
    assert len(sync.trace) == len(asynchronous.trace)
    for a, b in zip(sync.trace, asynchronous.trace, strict=True):
        assert {k: b.get(k) for k in a} == a, (a, b)


@pytest.mark.parametrize("script, options", [
    ({"latent_error": {2: 2.0, 3: 2.0, 8: 2.0}}, {}),  # replan, then a committed plan
    ({"latent_error": {2: 2.0, 3: 2.0, 8: 2.0}}, {"monitor": False}),
    ({"latent_error": {2: 2.0, 3: 2.0, 4: 2.0}}, {"commit_after_cut": False}),  # cut after cut
    ({"u_act": [1.0] + [0] * 7}, {}),  # pause, then a committed plan
    ({"u_act": [1.0] + [0] * 7}, {"commit_after_cut": False, "max_pauses": 2}),  # pauses, then forced
    ({"u_act": [0, 0.4, 0, 0, 0, 0, 0, 0], "values": [1, 0.1, 1, 1, 1]}, {"max_pauses": 0}),  # prune
])
def test_async_aurd_at_zero_latency_with_the_auto_threshold_is_sync_aurd(script, options):
    sync = episode("aurd", SyncConfig(), "0", policy=ScriptedPolicy(**script), steps=20, **options)
    asynchronous = episode("aurd", AsyncConfig(threshold="auto"), "0", policy=ScriptedPolicy(**script), steps=20,
                           **options)
    assert any(event != "complete" for _, event in sync.plans)
    same_decisions(sync, asynchronous)


def test_async_aurd_with_a_fixed_threshold_at_zero_latency_waits_for_the_plan():
    # threshold 2 at 0 ms: the answer sent with 2 actions left is here at once but waits until the plan has run its
    # horizon, then starts 2 actions in (a chunk from an observation 2 steps old); its first step is tested on
    # U_act alone, as the synchronous AURD's step 0 (its own actions have had no outcome yet)
    r = episode("aurd", AsyncConfig(threshold=2), "0", steps=12)
    assert played(r) == [(1, 0), (1, 1), (1, 2), (1, 3), (1, 4), (2, 2), (2, 3), (2, 4), (2, 5), (2, 6), (3, 2),
                         (3, 3)]
    assert r.plans == [(5, "complete"), (5, "complete")] and r.trace[5]["u_pred"] == 0.0


def test_the_auto_threshold_sends_so_that_the_chunk_lands_as_the_plan_runs_out():
    # d steps of delay: the threshold is d, so a query goes out when d actions remain (t = 5, 10, ... with H = 5)
    # and lands as the plan runs out; the arm idles only while the first chunk is in flight
    for ms, d in (("0", 0), ("100", 1), ("200", 2), ("300", 3), ("200:60", 2)):
        r = episode("fixed", AsyncConfig(threshold="auto"), ms, horizon=5, steps=30, seed=4)
        sent = [row["t"] for row in r.trace if "sent" in row]
        offsets = [row["offset"] for row in r.trace if row.get("replanned")]
        if ":" in ms:  # jitter: the threshold is the mean's 2 steps; a late answer costs idle steps, an early one
            assert 2 in offsets and set(offsets) != {2}  # takes over when it arrives
            continue
        assert sent == [0, 5, 10, 15, 20, 25] and offsets == [d] * 6, ms
        assert [row["t"] for row in r.trace if row.get("idle")] == list(range(d)), ms
    sync = episode("fixed", SyncConfig(), "0", horizon=5, steps=30)
    auto0 = episode("fixed", AsyncConfig(threshold="auto"), "0", horizon=5, steps=30)
    assert np.array_equal(sync.actions, auto0.actions) and sync.queries == auto0.queries


def test_the_auto_threshold_on_a_wall_clock_link_follows_the_measured_round_trips():
    from pivla.control.latency import WallClockLink

    link = WallClockLink(ScriptedPolicy(), 10)
    try:
        assert link.expected_delay_steps() == 0  # nothing measured yet
        link.stats.delays.extend([2, 2, 3])
        assert link.expected_delay_steps() == 3  # the mean (2.33 steps) rounded up
        link.stats.delays[:] = [2, 2]
        assert link.expected_delay_steps() == 2
    finally:
        link.close()


@pytest.mark.parametrize("threshold", [-1, "soon", 1.5, True])
def test_a_bad_threshold_is_named(threshold):
    from pivla.control.asynchronous import check_execution

    with pytest.raises(ValueError, match="execution.threshold must be 'auto' or a number of actions"):
        check_execution(AsyncConfig(threshold=threshold), executor_config("fixed"))


def test_async_aurd_at_latency_cuts_a_late_chunks_untrusted_first_step_instead_of_pausing():
    # every chunk's first executed step is untrusted on U_act; at 100 ms a chunk is one step late, so it answers
    # an older observation: AURD sends a query from this one at once (no pause: the answer can differ)
    u_act = [1.0] * 8
    r = episode("aurd", AsyncConfig(threshold="auto"), "100", policy=ScriptedPolicy(u_act=u_act), steps=10)
    cut = next(row for row in r.trace if row.get("cut"))
    assert cut["t"] == 1 and cut["sent"] == "replan" and cut["plan_step"] == 1 and cut.get("event") is None
    assert r.summary()["pauses"] == 0 and r.trace[2]["ended"] == "replan" and r.trace[2]["committed"]
    zero = episode("aurd", AsyncConfig(threshold="auto"), "0", policy=ScriptedPolicy(u_act=u_act), steps=10)
    assert zero.trace[0]["event"] == "pause" and zero.summary()["pauses"] >= 1


def test_trace_events_are_the_strings_on_disk():
    from pivla.control.math import Event

    r = episode("aurd", AsyncConfig(threshold="auto"), "100", policy=ScriptedPolicy(latent_error={2: 2.0}))
    text = json.dumps(r.trace)
    assert '"cut": "replan"' in text and '"sent": "threshold"' in text and '"ended": "replan"' in text
    assert all(type(v) is str for row in r.trace for k, v in row.items() if k in ("cut", "sent", "ended", "event")
               and v is not None)
    assert r.plans[0] == (2, Event.REPLAN) == (2, "replan") and r.summary()["replans"] == 1


# -- faults ---------------------------------------------------------------------------------------------------
def test_a_chunk_that_arrives_past_all_its_actions_is_dropped_and_counted():
    r = episode("fixed", AsyncConfig(threshold=2), "800", horizon=3, steps=20)  # 8 steps late, K = 8
    assert played(r) == ["."] * 20
    assert r.summary()["stale_chunks"] == 2 and r.summary()["idle_steps"] == 20


class MisdeliveringLink(SimulatedLink):
    """Also delivers, once, an answer to a query that is not in flight (another observation's chunk)."""

    strayed = False

    def arrivals(self, step):
        out = super().arrivals(step)
        if step == 4 and not self.strayed:
            self.strayed = True
            stray = {k: v.copy() for k, v in ScriptedPolicy().infer({}).items()}
            stray["actions"][:, 0] = 77.0
            out.append(Arrival(id=99, sent=3, step=4, output=stray))
        return out


def test_an_answer_for_another_observation_is_never_executed():
    from pivla.control.asynchronous import make_async_executor

    for name in ("fixed", "ensemble"):
        ex = make_async_executor(executor_config(name, **({"horizon": 3} if name == "fixed" else {})),
                                 AsyncConfig(threshold=2))
        ex.reset()
        policy = ScriptedPolicy()
        ex.link = MisdeliveringLink(policy, Latency(100.0), 10, seed=0)
        actions = [ex.act(policy, {"t": t}) for t in range(10)]
        assert ex.out_of_order == 1 and all(a[0] < 77 for a in actions), name
        assert "out_of_order" in ex.trace[4]["dropped"]


class LinkLostAfter(ScriptedPolicy):
    """Answers ``n`` queries, then the link is down: every query raises what RemotePolicy raises."""

    def __init__(self, n, **kw):
        super().__init__(**kw)
        self.n = n

    def infer(self, obs):
        if self.queries >= self.n:
            raise ConnectionError("pivla server at ws://x: connection lost, 2 reconnection attempt(s) failed")
        return super().infer(obs)


@pytest.mark.parametrize("name", ["fixed", "aurd", "ensemble"])
def test_a_lost_link_makes_the_arm_hold_within_the_chunks_horizon(name):
    options = {"horizon": 3} if name == "fixed" else {}
    r = episode(name, AsyncConfig(threshold=2), "100", policy=LinkLostAfter(1), **options)
    horizon = {"fixed": 3, "aurd": 5, "ensemble": 7}[name]  # ensemble: the chunk's K = 8 less the step it came late
    moving = [t for t, a in enumerate(played(r)) if a != "."]
    assert moving == list(range(1, 1 + horizon)), played(r)
    assert all(a == "." for a in played(r)[1 + horizon:])
    assert r.summary()["failed_queries"] >= 5 and r.summary()["idle_steps"] == 14 - horizon


# -- the twin: zero latency is today's episode; the evaluation records what latency costs ----------------------
@pytest.fixture(scope="module")
def twin_policy(tmp_path_factory):
    from pivla.policy import load_policy
    from tests.test_serving import write_run

    run = write_run(tmp_path_factory.mktemp("latency") / "run")
    return run, load_policy(run, device="cpu")


@pytest.fixture(scope="module")
def twin():
    from pivla.envs import make_env

    env = make_env("tabletop", "pick_place", 0, image_size=32)
    yield env
    env.close()


def _aurd_options(env, policy):
    """Thresholds inside this policy's U, so that AURD cuts plans (as tests/test_serving.py chooses them)."""
    probe = run_episode(env, policy, make_executor("aurd", tau_low=1e9, tau_high=1e9, v_thresh=-1e9), seed=3,
                        max_steps=20)
    u = [row["u"] for row in probe.trace]
    return {"tau_low": float(np.percentile(u, 30)), "tau_high": float(np.percentile(u, 80)), "v_thresh": 0.0}


@pytest.mark.parametrize("name", ["fixed", "aurd", "ensemble", "adahorizon"])
def test_zero_latency_reproduces_todays_twin_episode_step_for_step(twin_policy, twin, name):
    policy = twin_policy[1]
    options = _aurd_options(twin, policy) if name == "aurd" else {"horizon": 3} if name == "fixed" else {}
    today = run_episode(twin, policy, make_executor(name, **options), seed=5, max_steps=12)
    latency0 = run_episode(twin, policy, make_executor(name, **options), seed=5, max_steps=12,
                           execution=SyncConfig(), latency="0")
    assert np.array_equal(today.actions, latency0.actions)
    assert today.trace == latency0.trace and today.plans == latency0.plans
    if name == "aurd":
        assert any(event != "complete" for _, event in today.plans), today.plans
    asynchronous = run_episode(twin, policy, make_executor(name, **options), seed=5, max_steps=12,
                               execution=AsyncConfig(threshold="auto" if name == "aurd" else 0), latency="0")
    assert np.array_equal(today.actions, asynchronous.actions)


@pytest.mark.parametrize("seed", [3, 5, 8])
def test_async_aurd_at_zero_latency_decides_as_sync_aurd_on_the_twin(twin_policy, twin, seed):
    policy = twin_policy[1]
    options = _aurd_options(twin, policy)
    sync = run_episode(twin, policy, make_executor("aurd", **options), seed=seed, max_steps=30,
                       execution=SyncConfig(), latency="0")
    asynchronous = run_episode(twin, policy, make_executor("aurd", **options), seed=seed, max_steps=30,
                               execution=AsyncConfig(), latency="0")  # the default threshold: auto
    assert any(event != "complete" for _, event in sync.plans), sync.plans
    same_decisions(sync, asynchronous)


def test_latency_depends_on_the_seed_not_on_the_machine(twin_policy, twin):
    policy = twin_policy[1]
    runs = [run_episode(twin, policy, make_executor("fixed"), seed=s, max_steps=14, execution=AsyncConfig(),
                        latency="150:80") for s in (5, 5, 6)]
    assert np.array_equal(runs[0].actions, runs[1].actions) and runs[0].delays == runs[1].delays
    assert runs[0].delays != runs[2].delays


def test_eval_writes_the_timing_metrics_and_report_tabulates_them(twin_policy, tmp_path):
    from pivla.evaluation.runner import EvalConfig, evaluate
    from pivla.experiments.report import write_report

    run = str(twin_policy[0])
    out = tmp_path / "lat200-async" / "fixed"
    cfg = EvalConfig(policy=run, out=str(out), tasks="0", executor=executor_config("fixed"), episodes=2, max_steps=10,
                     videos=0, execution=AsyncConfig(threshold=1, seam="blend"), latency_ms="200:40")
    res = evaluate(cfg, progress=False)
    for key in ("steps_to_success_mean", "idle_steps", "idle_fraction", "queries_per_minute", "seam_jerk",
                "stale_chunks", "out_of_order_chunks", "failed_queries", "delay_steps_mean"):
        assert key in res, key
    assert res["latency_ms"] == "200:40" and res["execution"]["name"] == "async" and res["idle_steps"] >= 2
    assert {"success_rate", "replans", "control_hz", "queries_per_100_steps"} <= set(res)  # the keys before stay
    row = json.loads((out / "episodes.jsonl").read_text().splitlines()[0])
    assert row["idle_steps"] >= 2 and row["queries_per_minute"] > 0 and row["env_control_hz"] == 10.0
    sync = tmp_path / "lat200-sync" / "fixed"
    evaluate(dataclasses.replace(cfg, out=str(sync), execution=SyncConfig()), progress=False)
    text = write_report(tmp_path).read_text()
    assert "## Latency and execution" in text and "| lat200-async | fixed | async g=1 blend | 200:40 |" in text
    with pytest.raises(SystemExit, match="holds episodes of an evaluation with other settings.*latency_ms"):
        evaluate(dataclasses.replace(cfg, latency_ms="100"), progress=False)


@pytest.mark.parametrize("latency, problem", [("abc", "expected MEAN"), ("-100", ">= 0"), ("nan", "finite")])
def test_eval_refuses_bad_latency_in_one_line(latency, problem, tmp_path):
    from pivla.evaluation.runner import EvalConfig, evaluate

    with pytest.raises(SystemExit, match=f"--latency-ms '{latency}': .*{problem}") as e:
        evaluate(EvalConfig(policy="unused", out=str(tmp_path), latency_ms=latency), progress=False)
    assert "\n" not in str(e.value)


def test_cli_takes_execution_and_latency():
    import tyro

    from pivla.cli.app import TYRO_CONFIG, _choice_shorthand
    from pivla.evaluation.runner import EvalConfig

    argv = ["--policy", "p", "--out", "o", "--execution", "async", "--execution.threshold", "3",
            "--execution.seam", "blend", "--executor", "fixed", "--executor.horizon", "4", "--latency-ms", "200:20"]
    cfg = tyro.cli(EvalConfig, args=_choice_shorthand(EvalConfig, argv), config=TYRO_CONFIG)
    assert cfg.execution == AsyncConfig(threshold=3, seam="blend") and cfg.executor.horizon == 4
    assert cfg.latency_ms == "200:20"


class PrefixPolicy(ScriptedPolicy):
    """A scripted policy that reads actions in flight and records what each query carried."""

    spec = dataclasses.replace(ScriptedPolicy.spec, action_prefix=3)

    def __init__(self):
        super().__init__()
        self.told = []

    def infer(self, obs):
        prefix = obs.get("action_prefix")
        self.told.append(None if prefix is None else [(int(a[0]), int(a[1])) for a in prefix])
        return super().infer(obs)


@pytest.mark.parametrize("name", ["fixed", "aurd"])
def test_async_tells_a_policy_that_reads_them_the_actions_it_executes_while_the_query_is_out(name):
    policy = PrefixPolicy()
    options = {"horizon": 3}
    r = episode(name, AsyncConfig(), "200", policy=policy, **options)
    # 2 steps in flight (the auto threshold): each query after the first carries the 2 plan steps that execute
    # before its answer takes over, and that answer starts right after them
    assert policy.told[0] is None and len(policy.told) == r.queries
    assert policy.told[1:] == [[(k, 3), (k, 4)] for k in range(1, len(policy.told))]
    assert played(r)[2:8] == [(1, 2), (1, 3), (1, 4), (2, 2), (2, 3), (2, 4)]
    quiet = PrefixPolicy()
    episode(name, AsyncConfig(prefix=False), "200", policy=quiet, **options)
    assert set(map(str, quiet.told)) == {"None"}
    synchronous = PrefixPolicy()
    episode(name, SyncConfig(), "200", policy=synchronous, **options)
    assert set(map(str, synchronous.told)) == {"None"}
