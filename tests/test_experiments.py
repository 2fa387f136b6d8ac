"""The parts every study shares (pivla.experiments): the renderer's markdown, the condition registry, typed
recipes, plans, stages that skip what is done, and trainings as Ray tasks on a two-node cluster."""

import dataclasses
import json

import pytest

from pivla.control.executors import executor_config
from pivla.envs.backend import BackendConfig
from pivla.evaluation.runner import EvalConfig
from pivla.experiments import conditions
from pivla.experiments.plan import Evaluation, EvaluationPlan, eval_config
from pivla.experiments.recipes import Kind, Recipe, execution_variant
from pivla.experiments.render import Lines, Table, markdown
from pivla.experiments.stages import Evaluate, Train, train_all, training_resources
from pivla.experiments.studies import twin_config
from tests.conftest import tiny_train_config


def test_markdown_puts_one_blank_line_between_blocks():
    """A blank cell (None) and an empty one ("") are spelled as the reports always spelled them; a block of no
    lines keeps its blank line (a report whose figure list is empty ends in one)."""
    table = Table(["a", "b", "c"], [["1", "", "2"], ["**all**", None, "3"]], title="T", note="Note.")
    assert markdown(["# H", table, Lines(("- x", "- y")), "end"]) == (
        "# H\n\n## T\n\nNote.\n\n| a | b | c |\n|---|---|---|\n| 1 |  | 2 |\n| **all** | | 3 |\n\n- x\n- y\n\nend\n")
    assert markdown(["# H", "para", Lines(())]) == "# H\n\npara\n\n"


def test_the_registry_names_every_cell_once():
    assert conditions.twin("displace_object_4") == conditions.Cell("displace_object_4", "displace_object",
                                                                   "displace_object=4")
    assert conditions.twin("push_arm_0").perturb == "push_arm=0"
    assert conditions.twin("distraction_level_0").perturb is None  # level 0: the same scenes, nothing added
    assert conditions.twin("unseen_tasks").suite == "pick_place_unseen"
    assert conditions.event("displace_object", 6, suite="long").name == "long_displace_object_6"
    assert conditions.IN_DISTRIBUTION.with_realism("ideal").name == "in_distribution_ideal"
    scenes = conditions.recording("pushed", conditions.event("push_arm", 4))
    assert (scenes.condition, scenes.perturb) == ("push_arm", "randomized_scene,push_arm=4")
    with pytest.raises(ValueError, match="unknown twin condition"):
        conditions.twin("displace_object")
    sampled = conditions.libero("libero_10", init="random")
    assert sampled.eval_fields("ideal") == {"env": "libero", "suite": "libero_10", "perturb": None,
                                             "realism": "ideal", "libero_init": "random"}


def test_a_recipe_kind_is_a_field_and_what_follows_from_it_is_derived():
    recipes = twin_config.recipes(twin_config.BenchmarkConfig(demo_counts=(10, 30)))
    kinds = {name: r.kind for name, r in recipes.items()}
    assert kinds["main"] is Kind.HEADLINE and kinds["demos_30"] is Kind.DEMO_COUNT
    assert [n for n, r in recipes.items() if r.rollouts] == ["round2"]
    assert twin_config.by_variant(recipes)["full"] == "main"
    assert recipes["abl_il_only"].loss == {"use_sp": False, "use_rl": False, "use_recon": False}
    with pytest.raises(ValueError, match="demos is the demonstration count"):
        Recipe("main", Kind.HEADLINE, demos=10)
    with pytest.raises(ValueError, match="unknown training variant"):
        Recipe("x", Kind.ABLATION, variant="no_such")
    assert execution_variant("fixed") == execution_variant("fixed_h5")  # one executor, two stored labels


def test_a_plan_holds_each_evaluation_once_and_makes_its_config():
    cell = conditions.twin("unseen_env")
    a = Evaluation("main", cell, "aurd", executor_config("aurd"))
    b = Evaluation("main", cell, "fixed", executor_config("fixed"))
    plan = EvaluationPlan.of([a, b, a], split="validation", episodes=3)
    assert list(plan) == [a, b] and len(plan) == 2
    ec = eval_config(b, plan, policy="p", out="o", realism="servo", family=True, workers=2)
    assert (ec.seed_family, ec.split, ec.condition, ec.perturb, ec.realism, ec.episodes, ec.workers) == (
        "validation", "validation", "unseen_env", "unseen_env", "servo", 3, 2)
    legacy = eval_config(b, plan, policy="p", out="o", realism="servo", family=False, seed=7)
    assert (legacy.seed_family, legacy.condition, legacy.seed) == (None, None, 7)


def test_an_evaluation_is_done_with_its_episodes_and_recordings(tmp_path):
    ec = EvalConfig(policy="p", out=str(tmp_path / "ev"), tasks="0", record=str(tmp_path / "rec"))
    stage = Evaluate(ec, expected=2)
    assert not stage.done()
    (tmp_path / "ev").mkdir()
    (tmp_path / "ev" / "results.json").write_text(json.dumps({"episodes": 1}))
    assert not stage.done()  # fewer episodes than asked: the evaluation resumes
    (tmp_path / "ev" / "results.json").write_text(json.dumps({"episodes": 2}))
    assert not stage.done()  # the recordings were not merged yet
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "block_away_rollouts.hdf5").write_text("")
    assert stage.done() and stage() == {"episodes": 2}  # done: its results, nothing run


def test_a_training_asks_for_a_gpu_where_the_cluster_has_them():
    cfg = tiny_train_config("d", "o")
    assert training_resources(cfg, cluster_gpus=4, node_cpus=16) == {"num_gpus": 1, "num_cpus": 1}
    assert training_resources(cfg, cluster_gpus=0, node_cpus=16) == {"num_cpus": cfg.threads}
    assert training_resources(dataclasses.replace(cfg, threads=0), 0, 16) == {"num_cpus": 16}


@pytest.mark.timeout(900)
def test_trainings_as_ray_tasks_equal_local_ones_and_skip_what_is_done(synthetic_data, tmp_path):
    """Two trainings submitted at once to a two-node cluster (one CPU each: one training a node) give the
    weights a local training gives; a finished one is not run again."""
    ray = pytest.importorskip("ray")
    import torch
    from ray.cluster_utils import Cluster
    from safetensors.torch import load_file

    def config(name, seed):
        return tiny_train_config(synthetic_data, tmp_path / name, steps=4, batch_size=4, threads=1, seed=seed,
                                 eval_every=2, ckpt_every=2, log_every=2, value_refresh_every=2, warmup=1)

    train_all([Train(config("local", 1))])
    nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    nodes.add_node(num_cpus=1)
    nodes.wait_for_nodes()
    try:
        remote = BackendConfig(backend="ray", ray_address=nodes.address)
        stages = [Train(config("ray1", 1), remote), Train(config("ray2", 2), remote)]
        train_all(stages)
        assert all(s.done() for s in stages) and not ray.is_initialized()  # the driver left the cluster
        local, on_ray = load_file(tmp_path / "local" / "model.safetensors"), load_file(
            tmp_path / "ray1" / "model.safetensors")
        assert local.keys() == on_ray.keys() and all(torch.equal(local[k], on_ray[k]) for k in local)
        mtime = (tmp_path / "ray1" / "model.safetensors").stat().st_mtime_ns
        train_all(stages)  # done: nothing is submitted
        assert (tmp_path / "ray1" / "model.safetensors").stat().st_mtime_ns == mtime
    finally:
        nodes.shutdown()
