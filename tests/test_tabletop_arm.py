"""The arm's kinematic model: the MJCF agrees with the documented spec, IK reaches and respects limits, and the
NumPy kinematics reproduce MuJoCo's (the reference computed here with MuJoCo itself) bit for bit, so the twin's
IK, and with it its episodes, do not depend on which of the two ran."""

import itertools

import numpy as np
import pytest

from pivla import arm
from pivla.arm.kinematics import _check_q


@pytest.fixture(scope="module")
def mujoco():
    return pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def reference(mujoco):
    """The same damped-least-squares IK on MuJoCo's own kinematics (mj_kinematics, mj_jacSite)."""

    class MujocoKinematics(arm.Kinematics):
        def __init__(self, path=arm.ARM_XML):
            super().__init__(arm.read_mjcf(path))
            self.mj = mujoco.MjModel.from_xml_path(str(path))
            self.data = mujoco.MjData(self.mj)
            self.qadr = [self.mj.jnt_qposadr[self.mj.joint(n).id] for n in arm.JOINT_NAMES]
            self.dofadr = [self.mj.jnt_dofadr[self.mj.joint(n).id] for n in arm.JOINT_NAMES]
            self.site_id = self.mj.site(arm.EE_SITE).id

        def fk_mat(self, q):
            self.data.qpos[self.qadr] = _check_q(q)
            mujoco.mj_kinematics(self.mj, self.data)
            return self.data.site_xpos[self.site_id].copy(), self.data.site_xmat[self.site_id].reshape(3, 3).copy()

        def jacobian(self, q):
            self.fk_mat(q)
            mujoco.mj_comPos(self.mj, self.data)
            jacp, jacr = np.zeros((3, self.mj.nv)), np.zeros((3, self.mj.nv))
            mujoco.mj_jacSite(self.mj, self.data, jacp, jacr, self.site_id)
            return np.vstack([jacp[:, self.dofadr], jacr[:, self.dofadr]])

    return MujocoKinematics


def assert_same_bits(mine, ref, what):
    """Equal including the sign of zeros (an Euler angle of +-pi hangs on it), with the largest difference shown."""
    mine, ref = np.asarray(mine, float), np.asarray(ref, float)
    assert mine.shape == ref.shape, what
    if not np.array_equal(mine.view(np.int64), ref.view(np.int64)):
        raise AssertionError(f"{what} differs from MuJoCo's by up to {np.max(np.abs(mine - ref)):.3g}: "
                             f"the twin's IK would no longer reproduce its recorded episodes\n{mine}\n{ref}")


def joint_samples(n, seed=0):
    """Random joint vectors (some beyond the limits) and every corner of quarter turns on the first joints."""
    rng = np.random.default_rng(seed)
    corners = [np.array(c + (0.3, -0.2, 0.1)) for c in itertools.product((0.0, np.pi / 2, -np.pi / 2, np.pi), repeat=3)]
    lo, hi = arm.JOINT_LIMITS[:, 0] - 1, arm.JOINT_LIMITS[:, 1] + 1
    return [np.zeros(6), *corners, *(rng.uniform(lo, hi) for _ in range(n))]


def test_mjcf_matches_documented_spec(mujoco):
    model = arm.load_model()
    compiled = mujoco.MjModel.from_xml_path(str(arm.ARM_XML))
    for name, (lo, hi) in zip(arm.JOINT_NAMES, arm.JOINT_LIMITS):
        assert np.allclose(model.joint(name)[1].range, [lo, hi], atol=1e-4), name
        assert np.allclose(compiled.actuator_ctrlrange[compiled.actuator(name).id], [lo, hi], atol=1e-4), name
    assert model.joint("finger_left")[1].range == (0.0, arm.GRIPPER_OPEN)
    pos, _ = arm.forward_kinematics(arm.ZERO_POSITION)
    assert np.allclose(pos, [0, 0, arm.LINK_LENGTHS["shoulder_height"] + arm.REACH], atol=1e-6)
    assert arm.REACH == pytest.approx(0.382)


def test_model_compiles_like_mujoco(mujoco):
    """Frames, joint axes, masses and centres of mass read from the MJCF equal MuJoCo's compiled model."""
    model = arm.load_model()
    compiled = mujoco.MjModel.from_xml_path(str(arm.ARM_XML))
    assert [b.name for b in model.bodies] == [compiled.body(i).name for i in range(compiled.nbody)]
    for i, body in enumerate(model.bodies):
        assert body.parent == (compiled.body_parentid[i] if i else -1)
        for mine, ref, what in ((body.pos, compiled.body_pos[i], "pos"), (body.quat, compiled.body_quat[i], "quat"),
                                (body.mass, compiled.body_mass[i], "mass"), (body.ipos, compiled.body_ipos[i], "ipos"),
                                (model.subtree_mass[i], compiled.body_subtreemass[i], "subtree mass")):
            assert_same_bits(mine, ref, f"body {body.name} {what}")
        for joint in body.joints:
            ref = compiled.joint(joint.name)
            assert ref.bodyid[0] == i
            assert_same_bits(joint.axis, ref.axis, f"joint {joint.name} axis")
            assert_same_bits(joint.range, ref.range, f"joint {joint.name} range")
    site, ref = model.site(arm.EE_SITE), compiled.site(arm.EE_SITE)
    assert site.body == ref.bodyid[0]
    assert_same_bits(site.pos, ref.pos, "site pos")
    assert_same_bits(site.quat, ref.quat, "site quat")


def test_forward_kinematics_and_jacobian_are_mujocos(reference):
    ours, theirs = arm.Kinematics(), reference()
    for q in joint_samples(1500):
        pos, mat = ours.fk_mat(q)
        ref_pos, ref_mat = theirs.fk_mat(q)
        jac, ref_jac = ours.jacobian(q), theirs.jacobian(q)
        np.testing.assert_allclose(pos, ref_pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(mat, ref_mat, rtol=0, atol=1e-12)
        np.testing.assert_allclose(jac, ref_jac, rtol=0, atol=1e-12)
        assert_same_bits(pos, ref_pos, f"tool position at {q}")
        assert_same_bits(mat, ref_mat, f"tool rotation at {q}")
        assert_same_bits(jac, ref_jac, f"Jacobian at {q}")
        assert_same_bits(ours.forward_kinematics(q)[1], theirs.forward_kinematics(q)[1], f"Euler angles at {q}")


def test_jacobian_is_the_derivative_of_forward_kinematics():
    kin, rng = arm.Kinematics(), np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(arm.JOINT_LIMITS[:, 0], arm.JOINT_LIMITS[:, 1])
        jac, (pos, mat), h = kin.jacobian(q), kin.fk_mat(q), 1e-6
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            pos2, mat2 = kin.fk_mat(q + dq)
            np.testing.assert_allclose((pos2 - pos) / h, jac[:3, i], atol=1e-5)
            np.testing.assert_allclose(arm.rotvec_from_mat(mat2 @ mat.T) / h, jac[3:, i], atol=1e-5)


def test_rotation_helpers_are_mujocos(mujoco):
    rng = np.random.default_rng(4)
    mats = [arm.euler_to_mat(rng.uniform(-4, 4, 3)) for _ in range(2000)]
    mats += [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]  # angle 0 and pi
    for mat in mats:
        quat, vel = np.empty(4), np.empty(3)
        mujoco.mju_mat2Quat(quat, mat.reshape(9))
        mujoco.mju_quat2Vel(vel, quat, 1.0)
        assert_same_bits(arm.rotvec_from_mat(mat), vel, f"rotvec of {mat}")
    vecs = [rng.normal(size=3) * rng.uniform(0, 3.5) for _ in range(2000)] + [np.zeros(3), np.array([0, 0, np.pi])]
    for vec in vecs:
        angle, quat, mat = np.linalg.norm(vec), np.array([1.0, 0, 0, 0]), np.empty(9)
        if angle > 1e-12:
            mujoco.mju_axisAngle2Quat(quat, vec / angle, angle)
        mujoco.mju_quat2Mat(mat, quat)
        assert_same_bits(arm.mat_from_rotvec(vec), mat.reshape(3, 3), f"matrix of rotvec {vec}")
        np.testing.assert_allclose(arm.mat_from_rotvec(vec) @ vec, vec, atol=1e-12)  # a rotation fixes its axis


def test_solve_ik_and_home_are_mujocos(reference):
    ours, theirs = arm.Kinematics(), reference()
    rng = np.random.default_rng(5)
    home = arm.home_q()
    assert_same_bits(home, theirs.solve_ik(*arm.HOME_POSE, q0=np.array([0.0, 0.4, 1.6, 0.0, 1.1, 0.0]),
                                            iterations=200)[0], "home pose")
    for _ in range(150):
        target = rng.uniform([0.0, -0.3, -0.05], [0.35, 0.3, 0.4])
        euler = rng.uniform([-0.5, -0.5, -np.pi], [0.5, 0.5, np.pi])
        q0 = arm.clip_to_limits(home + rng.uniform(-0.5, 0.5, 6))
        q, pos_err, rot_err = ours.solve_ik(target, euler, q0)
        ref_q, ref_pos_err, ref_rot_err = theirs.solve_ik(target, euler, q0)
        np.testing.assert_allclose(q, ref_q, rtol=0, atol=1e-9)
        assert_same_bits(q, ref_q, f"IK solution for {target}, {euler}")
        assert (pos_err, rot_err) == (ref_pos_err, ref_rot_err)


def test_twin_episodes_do_not_depend_on_the_kinematics_backend(reference):
    from pivla.envs.rollout import run_episode
    from pivla.envs.tabletop import make_env
    from pivla.envs.tabletop.expert import make_expert

    episodes = []
    for backend in (arm.Kinematics, reference):
        env = make_env("pick_place", 0, realism="servo", perturb="push_arm=4", render=False)
        env.kin = backend()
        env.perturber.kin = backend()
        episodes.append(run_episode(env, make_expert(0.3), seed=3))
        env.close()
    ours, theirs = episodes
    assert len(ours.actions) > 10
    np.testing.assert_array_equal(ours.actions, theirs.actions)
    for key in ours.obs:
        np.testing.assert_array_equal(ours.obs[key], theirs.obs[key], err_msg=key)


def _random_mjcf(rng) -> str:
    """An arm-like tree with everything the reader models: offsets, rotated bodies (quat, euler in degrees with
    another sequence, axisangle), off-centre and tilted joint axes, two joints on one body, a slide joint, a
    joint outside the arm held at its ref, default classes and several geoms per body."""
    f = lambda *v: " ".join(f"{x:.6g}" for x in v)  # noqa: E731
    pos = lambda: f(*rng.uniform(-0.05, 0.1, 3))  # noqa: E731
    axis = lambda: f(*rng.normal(size=3))  # noqa: E731
    return f"""<mujoco>
  <compiler angle="degree" eulerseq="zYx"/>
  <default>
    <joint axis="0 1 0"/>
    <geom density="800"/>
    <default class="light"><geom type="box" density="300"/><joint type="slide"/></default>
  </default>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <body name="a" pos="{pos()}" quat="{f(*rng.normal(size=4))}">
      <joint name="base_yaw" axis="{axis()}" pos="{pos()}" range="-90 90"/>
      <geom type="capsule" fromto="{f(*rng.uniform(-0.05, 0.05, 3))} {f(*rng.uniform(0.1, 0.2, 3))}" size="0.02"/>
      <geom class="light" size="0.01 0.02 0.03" pos="{pos()}"/>
      <body name="b" pos="{pos()}" euler="{f(*rng.uniform(-180, 180, 3))}" childclass="light">
        <joint name="shoulder_pitch" type="hinge" axis="{axis()}"/>
        <joint name="elbow_pitch" type="hinge" pos="{pos()}"/>
        <geom type="sphere" size="0.03" pos="{pos()}"/>
        <geom type="cylinder" size="0.01 0.04" pos="{pos()}" mass="0.2"/>
        <body name="c" pos="{pos()}" axisangle="{axis()} {rng.uniform(-180, 180):.6g}">
          <joint name="forearm_roll" axis="{axis()}" range="-0.1 0.1"/>
          <geom type="ellipsoid" size="0.02 0.03 0.01"/>
          <body name="d" pos="{pos()}">
            <joint name="held" type="hinge" ref="{rng.uniform(-40, 40):.6g}"/>
            <inertial pos="{pos()}" mass="0.3" diaginertia="1e-4 1e-4 1e-4"/>
            <body name="e" pos="{pos()}" quat="{f(*rng.normal(size=4))}">
              <joint name="wrist_pitch" type="hinge" axis="{axis()}" pos="{pos()}"/>
              <joint name="wrist_roll" type="hinge" axis="{axis()}"/>
              <geom type="box" size="0.02 0.01 0.03" pos="{pos()}" euler="10 20 30"/>
              <site name="ee" pos="{pos()}" euler="{f(*rng.uniform(-180, 180, 3))}"/>
              <camera name="cam" pos="0 0 0.1"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>"""


def test_reader_handles_general_mjcf_like_mujoco(mujoco, tmp_path):
    rng = np.random.default_rng(6)
    for i in range(6):
        path = tmp_path / f"tree{i}.xml"
        path.write_text(_random_mjcf(rng))
        compiled = mujoco.MjModel.from_xml_path(str(path))
        model = arm.read_mjcf(path)
        for b, body in enumerate(model.bodies):
            np.testing.assert_allclose(body.mass, compiled.body_mass[b], rtol=1e-12)
            np.testing.assert_allclose(body.ipos, compiled.body_ipos[b], atol=1e-12)
        _, slide = model.joint("forearm_roll")
        assert slide.kind == "slide" and slide.range == (-0.1, 0.1)
        np.testing.assert_allclose(model.joint("base_yaw")[1].range, np.radians([-90, 90]), atol=1e-12)
        ours = arm.Kinematics(model)
        data = mujoco.MjData(compiled)
        qadr = [compiled.jnt_qposadr[compiled.joint(n).id] for n in arm.JOINT_NAMES]
        dofadr = [compiled.jnt_dofadr[compiled.joint(n).id] for n in arm.JOINT_NAMES]
        site = compiled.site("ee").id
        for q in rng.uniform(-2, 2, (50, 6)):
            data.qpos[qadr] = q
            mujoco.mj_kinematics(compiled, data)
            mujoco.mj_comPos(compiled, data)
            jacp, jacr = np.zeros((3, compiled.nv)), np.zeros((3, compiled.nv))
            mujoco.mj_jacSite(compiled, data, jacp, jacr, site)
            pos, mat = ours.fk_mat(q)
            np.testing.assert_allclose(pos, data.site_xpos[site], atol=1e-12)
            np.testing.assert_allclose(mat, data.site_xmat[site].reshape(3, 3), atol=1e-12)
            np.testing.assert_allclose(ours.jacobian(q), np.vstack([jacp[:, dofadr], jacr[:, dofadr]]), atol=1e-12)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ('<body name="x"><joint name="j" type="ball"/><geom size="0.1"/></body>', "ball joint"),
        ('<body name="x"><freejoint/><geom size="0.1"/></body>', "free joint"),
        ('<body name="x"><geom type="mesh" mesh="m"/></body>', "type mesh"),
        ('<frame pos="0 0 1"><body name="x"/></frame>', "<frame> is not supported"),
        ('<body name="x" xyaxes="1 0 0 0 1 0"><geom size="0.1"/></body>', "uses xyaxes"),
        ('<body name="x" quat="0 0 0 0"><geom size="0.1"/></body>', "zero quaternion"),
        ('<body name="x"><geom class="nope" size="0.1"/></body>', "unknown class 'nope'"),
        ('<body name="x" pos="0 0"><geom size="0.1"/></body>', "needs 3 numbers"),
    ],
)
def test_reader_rejects_what_it_does_not_model(tmp_path, body, message):
    path = tmp_path / "bad.xml"
    path.write_text(f"<mujoco><worldbody>{body}</worldbody></mujoco>")
    with pytest.raises(arm.MjcfError, match=message):
        arm.read_mjcf(path)


def test_reader_names_missing_and_malformed_files(tmp_path):
    with pytest.raises(arm.MjcfError, match="cannot read MJCF"):
        arm.read_mjcf(tmp_path / "missing.xml")
    (tmp_path / "bad.xml").write_text("<mujoco><worldbody>")
    with pytest.raises(arm.MjcfError, match="cannot read MJCF"):
        arm.read_mjcf(tmp_path / "bad.xml")
    (tmp_path / "other.xml").write_text("<robot/>")
    with pytest.raises(arm.MjcfError, match="expected <mujoco>"):
        arm.read_mjcf(tmp_path / "other.xml")
    with pytest.raises(KeyError, match="no joint 'elbow'"):
        arm.load_model().joint("elbow")


def test_euler_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        e = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        assert np.allclose(arm.mat_to_euler(arm.euler_to_mat(e)), e, atol=1e-9)
        assert np.allclose(arm.mat_from_rotvec(arm.rotvec_from_mat(arm.euler_to_mat(e))), arm.euler_to_mat(e),
                           atol=1e-9)


def test_home_pose_is_top_down():
    pos, euler = arm.forward_kinematics(arm.home_q())
    assert np.allclose(pos, arm.HOME_POSE[0], atol=1e-3)
    assert np.allclose(euler, 0, atol=1e-2)


def test_ik_reaches_reachable_targets_within_limits():
    rng = np.random.default_rng(1)
    kin = arm.Kinematics()
    home = arm.home_q()
    for _ in range(40):
        q_true = arm.clip_to_limits(home + rng.uniform(-0.5, 0.5, 6))
        pos, euler = kin.forward_kinematics(q_true)
        q, pos_err, rot_err = kin.solve_ik(pos, euler, home, iterations=100)
        assert pos_err < 1e-3 and rot_err < 1e-2, (q_true, q, pos_err, rot_err)
        assert np.all(q >= arm.JOINT_LIMITS[:, 0]) and np.all(q <= arm.JOINT_LIMITS[:, 1])
        assert np.allclose(kin.forward_kinematics(q)[0], pos, atol=1e-3)


def test_ik_covers_the_tabletop_workspace_top_down():
    """Every grasp point of the task layouts (tool-centre radius 0.12-0.27 m) is reachable pointing down."""
    for x in (0.12, 0.18, 0.24, 0.27):
        for y in (-0.12, 0.0, 0.12):
            if np.hypot(x, y) > 0.27:
                continue
            yaw = np.arctan2(y, x)
            _, pos_err, rot_err = arm.solve_ik(np.array([x, y, 0.016]), np.array([0, 0, yaw]))
            assert pos_err < 1e-3 and rot_err < 1e-2, (x, y)


def test_ik_respects_joint_limits_on_unreachable_targets():
    rng = np.random.default_rng(2)
    q, pos_err, _ = arm.solve_ik(np.array([1.0, 0.0, 0.0]), np.zeros(3))
    assert pos_err > 0.4
    assert np.all(q >= arm.JOINT_LIMITS[:, 0] - 1e-12) and np.all(q <= arm.JOINT_LIMITS[:, 1] + 1e-12)
    kin = arm.Kinematics()
    for _ in range(30):
        q0 = rng.uniform(arm.JOINT_LIMITS[:, 0], arm.JOINT_LIMITS[:, 1])
        q1 = kin.ik_step(q0, rng.uniform(-0.5, 0.5, 3), arm.euler_to_mat(rng.uniform(-3, 3, 3)))
        assert np.all(q1 >= arm.JOINT_LIMITS[:, 0] - 1e-12) and np.all(q1 <= arm.JOINT_LIMITS[:, 1] + 1e-12)


def test_bad_joint_vectors_are_rejected():
    with pytest.raises(ValueError, match="shape"):
        arm.forward_kinematics(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        arm.forward_kinematics(np.array([0, 0, np.nan, 0, 0, 0]))
    with pytest.raises(ValueError, match="finite"):
        arm.solve_ik(np.array([np.nan, 0, 0]), np.zeros(3))
