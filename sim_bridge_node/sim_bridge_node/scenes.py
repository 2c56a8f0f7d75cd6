"""MuJoCo scenes of the task files (nf_core.task_spec, config/tasks/), plus the 2-D block and a free-space
scene, built with ``mujoco.MjSpec``.

World frame: the Panda's base (``panda_link0``) at the origin on the table plane z = 0, x forward.

- a gear task (``gear``, ``gear_clamp``, a user's file with ``part: kind: gear``): a stepped steel shaft
  on the table: a square base block (at least 100 x 100 mm, 40 mm high), a shoulder up to the pin's
  foot, then the pin, ``shaft_length`` long, its top face at the fixture's ``position``; the gear seats on
  the shoulder at full depth. With a ``clamp``, a steel jaw stands between the start and the shaft.
- a peg task (``peg``): a block with a square hole, its mouth at the fixture's ``position``, made of a
  base and four wall boxes; the arm holds the peg instead of the gear.
- ``block``: no arm. A 50 mm, 1 kg cube on two slide joints (x and z) with force motors, above a
  slot 52 mm wide (1 mm per side) and 50 mm deep cut between two wall boxes.
- ``free``: the Panda with the gear task's gear, the table plane and lights, nothing else.

Contacts: every solid geom of a scene uses ``CONTACT_SOLREF``/``CONTACT_SOLIMP`` and the task's sliding
friction (``CONTACT_FRICTION``'s torsional and rolling parts), which keeps resting penetration well
below 0.5 mm under the forces the arm can push with; convex pairs yield one contact each (multi-point
convex collision off, see ``_add_lights_and_table``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from nf_core import panda_spec
from nf_core.task_spec import Clamp, Fixture, TaskFileError, TaskSpec, load_task
from sim_bridge_node.held_parts import HeldPart, add_gear, add_peg
from sim_bridge_node.panda_model import CONTACT_MOVING, TIMESTEP, load_panda_spec

TASKS = ("gear", "peg", "block", "free", "gear_clamp")  # the built-in ones; any task file is a task too

# Contact model (all solid geoms): stiff, critically damped soft contacts.
CONTACT_SOLREF = np.array([0.004, 1.0])  # time constant (>= 2 time steps), damping ratio
CONTACT_SOLIMP = np.array([0.95, 0.99, 0.0005, 0.5, 2.0])
CONTACT_FRICTION = np.array([0.4, 0.005, 0.0001])  # sliding (a task file sets its own), torsional, rolling
CONTACT_CONDIM = 3

# Fixture details a task file does not set (its sizes, place and the starts are the task file's:
# nf_core.task_spec, config/tasks/).
FIXTURE_BASE_HALF = 0.05  # m, least half side of the shaft's square base block
HOLE_BLOCK_HALF = 0.04  # m, least half side of the hole block
# Seed of the start's inverse kinematics: the gear task's start posture (hand down, elbow up).
IK_SEED = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])  # rad

# 2-D block insertion.
BLOCK_SIZE = 0.05  # m, cube side
BLOCK_MASS = 1.0  # kg
SLOT_WIDTH = BLOCK_SIZE + 0.002  # m, 2 mm clearance in total
SLOT_DEPTH = 0.05  # m
SLOT_TOP = 0.10  # m, z of the slot's mouth (the wall tops)
SLOT_WALL_HALF_LENGTH = 0.25  # m
BLOCK_FORCE_LIMIT = 30.0  # N, per axis
BLOCK_START_MEAN = np.array([0.10, 0.25])  # m, (x, z) of the block relative to fully inserted
BLOCK_START_STD = np.array([0.05, 0.10])  # m
BLOCK_RANGE = np.array([[-0.35, 0.35], [-0.001, 0.60]])  # m, slide joint limits (x, z)

# Contact sensor on the held part: net force it exerts on everything else (world frame).
CONTACT_FORCE_SENSOR = "held_contact_force"

FIXTURE_RGBA = np.array([0.55, 0.58, 0.62, 1.0])
PIN_RGBA = np.array([0.75, 0.78, 0.82, 1.0])
BLOCK_RGBA = np.array([0.85, 0.2, 0.15, 1.0])


@dataclass
class Scene:
    """A compiled scene with the facts an environment needs (all names, world-frame geometry)."""

    task: str
    model: mujoco.MjModel
    joint_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    tcp_site: str
    held_body: str  # body whose contacts count as the held part's (gear, peg, block)
    fixture_body: str  # "" for the free scene
    q_mean: np.ndarray  # fixed start configuration
    goal_position: np.ndarray  # TCP position at full insertion (world)
    insertion_top: float  # z of the fixture mouth; depth = insertion_top - tcp z
    insertion_axis_xy: np.ndarray  # lateral position of the insertion axis
    lateral_tolerance: float  # TCP this close to the axis (per axis) counts as in the opening
    success_depth: float  # m
    held_part: HeldPart | None = None
    start_std: float | None = None  # joint std of sampled starts (None: the environment's default)
    start_region: np.ndarray | None = None  # (2, 3) TCP box [lo, hi] a sampled start must lie in
    camera: dict = field(default_factory=dict)  # free camera for pictures: lookat, distance, ...
    kind: str = ""  # gear | peg (the part) | block | free
    spec: TaskSpec | None = None  # the task file it was built from (arm tasks)


def _material(spec: mujoco.MjSpec) -> None:
    tex = spec.add_texture()
    tex.name = "table_checker"
    tex.type = mujoco.mjtTexture.mjTEXTURE_2D
    tex.builtin = mujoco.mjtBuiltin.mjBUILTIN_CHECKER
    tex.rgb1 = [0.30, 0.36, 0.44]
    tex.rgb2 = [0.36, 0.42, 0.50]
    tex.width = 512
    tex.height = 512
    mat = spec.add_material()
    mat.name = "table_material"
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "table_checker"
    mat.texrepeat = [8.0, 8.0]
    mat.reflectance = 0.0
    sky = spec.add_texture()
    sky.name = "sky"
    sky.type = mujoco.mjtTexture.mjTEXTURE_SKYBOX
    sky.builtin = mujoco.mjtBuiltin.mjBUILTIN_GRADIENT
    sky.rgb1 = [0.85, 0.88, 0.92]
    sky.rgb2 = [0.55, 0.6, 0.68]
    sky.width = 256
    sky.height = 256


def _add_lights_and_table(spec: mujoco.MjSpec, center: np.ndarray) -> None:
    _material(spec)
    # One contact per convex pair: MuJoCo's multi-point convex collision produced spurious deep
    # contacts (up to 7 mm, with kN impulses) between the gear's boxes and the shoulder's flat
    # cylinder cap. The gear's 16 segments still give up to 16 support points; box-box pairs keep
    # their own multi-point collider.
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_MULTICCD
    world = spec.worldbody
    table = world.add_geom()
    table.name = "table"
    table.type = mujoco.mjtGeom.mjGEOM_PLANE
    table.size = [1.5, 1.5, 0.05]
    table.material = "table_material"
    _make_fixed_solid(table)
    for k, (offset, diffuse) in enumerate(
        [((0.6, -0.8, 1.6), 0.6), ((-0.6, 0.9, 1.4), 0.35), ((0.2, 0.0, 2.0), 0.3)]
    ):
        light = world.add_light()
        light.name = f"light_{k}"
        light.pos = np.asarray(center) + np.asarray(offset)
        light.dir = -np.asarray(offset) / np.linalg.norm(offset)
        light.diffuse = [diffuse] * 3
        light.specular = [0.2] * 3
        light.castshadow = k == 0
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960


def _add_contact_sensor(spec: mujoco.MjSpec, body_name: str) -> None:
    sensor = spec.add_sensor()
    sensor.name = CONTACT_FORCE_SENSOR
    sensor.type = mujoco.mjtSensor.mjSENS_CONTACT
    sensor.objtype = mujoco.mjtObj.mjOBJ_BODY
    sensor.objname = body_name
    # intprm: data fields (bit mask: force), reduction (3 = net force), number of slots
    sensor.intprm = [1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE), 3, 1]


def _make_fixed_solid(geom: mujoco.MjsGeom) -> None:
    geom.contype = 0
    geom.conaffinity = CONTACT_MOVING
    contact_params(geom)


def contact_params(geom: mujoco.MjsGeom) -> None:
    """The task contacts' solref, solimp, friction and condim on ``geom`` (used by the franky-sim
    gear fixture too)."""
    geom.solref = CONTACT_SOLREF
    geom.solimp = CONTACT_SOLIMP
    geom.friction = CONTACT_FRICTION
    geom.condim = CONTACT_CONDIM


def _box(body: mujoco.MjsBody, name: str, half: tuple, pos: tuple, rgba: np.ndarray) -> mujoco.MjsGeom:
    geom = body.add_geom()
    geom.name = name
    geom.type = mujoco.mjtGeom.mjGEOM_BOX
    geom.size = list(half)
    geom.pos = list(pos)
    geom.rgba = rgba
    _make_fixed_solid(geom)
    return geom


def _cylinder(body: mujoco.MjsBody, name: str, radius: float, z0: float, z1: float, rgba) -> mujoco.MjsGeom:
    geom = body.add_geom()
    geom.name = name
    geom.type = mujoco.mjtGeom.mjGEOM_CYLINDER
    geom.size = [radius, 0.5 * (z1 - z0), 0.0]
    geom.pos = [0.0, 0.0, 0.5 * (z0 + z1)]
    geom.rgba = rgba
    _make_fixed_solid(geom)
    return geom


def add_shaft(spec: mujoco.MjSpec, fixture: Fixture | None = None) -> None:
    """Stepped shaft: base block, shoulder, pin (convex pieces: one box, two cylinders), its top face at
    the fixture's position (default: the gear task's; ``nf_bringup.testing.franky`` moves a copy)."""
    fixture = fixture or Fixture()
    x, y, top = fixture.position
    body = spec.worldbody.add_body()
    body.name = "shaft"
    body.pos = [x, y, 0.0]
    pin_bottom = top - fixture.shaft_length
    base_top = min(0.04, pin_bottom - 0.005)
    half = max(FIXTURE_BASE_HALF, fixture.shoulder_radius + 0.01)
    _box(body, "shaft_base", (half, half, 0.5 * base_top), (0.0, 0.0, 0.5 * base_top), FIXTURE_RGBA)
    _cylinder(body, "shaft_shoulder", fixture.shoulder_radius, base_top, pin_bottom, PIN_RGBA)
    _cylinder(body, "shaft_pin", fixture.shaft_radius, pin_bottom, top, PIN_RGBA)


def _add_hole(spec: mujoco.MjSpec, fixture: Fixture) -> None:
    """Block with a square hole: a base and four wall boxes, the mouth at the fixture's position."""
    x, y, top = fixture.position
    body = spec.worldbody.add_body()
    body.name = "hole"
    body.pos = [x, y, 0.0]
    bottom = top - fixture.hole_depth
    a = fixture.hole_half_width
    b = max(HOLE_BLOCK_HALF, a + 0.02)  # walls at least 2 cm thick
    _box(body, "hole_base", (b, b, 0.5 * bottom), (0.0, 0.0, 0.5 * bottom), FIXTURE_RGBA)
    zc, hz = 0.5 * (bottom + top), 0.5 * fixture.hole_depth
    wall = 0.5 * (b - a)
    _box(body, "hole_wall_px", (wall, b, hz), (a + wall, 0.0, zc), PIN_RGBA)
    _box(body, "hole_wall_nx", (wall, b, hz), (-a - wall, 0.0, zc), PIN_RGBA)
    _box(body, "hole_wall_py", (a, wall, hz), (0.0, a + wall, zc), PIN_RGBA)
    _box(body, "hole_wall_ny", (a, wall, hz), (0.0, -a - wall, zc), PIN_RGBA)


def add_clamp(spec: mujoco.MjSpec, clamp: Clamp, fixture_y: float) -> None:
    """The clamp jaw of a task with one: a box from the table up to its top, across the approach."""
    body = spec.worldbody.add_body()
    body.name = "clamp"
    body.pos = [clamp.center_x, fixture_y, 0.0]
    _box(body, "clamp_jaw", (clamp.half_thickness, clamp.half_length, 0.5 * clamp.top), (0.0, 0.0, 0.5 * clamp.top),
         FIXTURE_RGBA)


def _arm_scene(task: TaskSpec, free: bool = False) -> Scene:
    """The arm holding the task's part, the task's fixture (none when ``free``) and the table."""
    spec = load_panda_spec()
    hand = spec.body(panda_spec.HAND_FRAME)
    part = task.part
    held = add_peg(hand, part) if part.kind == "peg" else add_gear(hand, part)
    for geom in spec.body(held.body).geoms:
        if geom.contype:
            contact_params(geom)
    for body in spec.bodies:  # arm links may touch the table and fixtures with the same model
        if body.name.startswith("panda_"):
            for geom in body.geoms:
                contact_params(geom)
    center = task.top
    _add_lights_and_table(spec, center)
    fixture = ""
    if free:
        pass
    elif part.kind == "gear":
        add_shaft(spec, task.fixture)
        fixture = "shaft"
        if task.clamp is not None:
            add_clamp(spec, task.clamp, task.fixture.position[1])
        # The closed fingertip pads reach 9.5 mm into the bore's upper end (they "hold" the gear
        # there); the pin passes between them at full depth instead of stopping on them.
        for finger in ("panda_leftfinger", "panda_rightfinger"):
            exclude = spec.add_exclude()
            exclude.bodyname1 = finger
            exclude.bodyname2 = "shaft"
    else:
        _add_hole(spec, task.fixture)
        fixture = "hole"
    if task.friction != CONTACT_FRICTION[0]:  # the task's sliding friction on every contact geom
        for geom in spec.geoms:
            if np.array_equal(geom.friction, CONTACT_FRICTION):
                geom.friction = [task.friction, *CONTACT_FRICTION[1:]]
    _add_contact_sensor(spec, held.body)
    model = spec.compile()
    if task.start.joints is not None:
        q_mean = np.asarray(task.start.joints, dtype=float)
    else:
        q_mean = start_joints(model, held.tcp_site, task.start_tcp)
    start_region = None if task.start.region is None else np.array(task.start.region, dtype=float)
    camera = {"lookat": center + [0.0, 0.0, 0.03], "distance": 0.45, "azimuth": 145.0, "elevation": -24.0}
    if free:
        camera = {"lookat": np.array([0.25, 0.0, 0.35]), "distance": 1.7, "azimuth": 140.0, "elevation": -20.0}
    return Scene(
        task="free" if free else task.name,
        model=model,
        joint_names=panda_spec.JOINT_NAMES,
        actuator_names=tuple(f"{n}_motor" for n in panda_spec.JOINT_NAMES),
        tcp_site=held.tcp_site,
        held_body=held.body,
        fixture_body=fixture,
        q_mean=q_mean,
        goal_position=task.goal_position,
        insertion_top=float(task.top[2]),
        insertion_axis_xy=task.top[:2].copy(),
        lateral_tolerance=task.lateral_tolerance,
        success_depth=task.success_depth,
        held_part=held,
        start_std=task.start.joint_std,
        start_region=start_region,
        camera=camera,
        kind="free" if free else part.kind,
        spec=task,
    )


def start_joints(model: mujoco.MjModel, tcp_site: str, tcp: np.ndarray, seed: np.ndarray = IK_SEED,
                 tolerance: float = 1e-5) -> np.ndarray:
    """Joints (rad) that put ``tcp_site`` at ``tcp`` (m, world) with the hand pointing down
    (``panda_spec.INSERTION_ROTATION``), by damped least squares on the scene's own kinematics from
    ``seed``, within the joint limits. Raises ``TaskFileError`` when no such pose is found (out of reach)."""
    names = panda_spec.JOINT_NAMES
    qadr = np.array([model.joint(n).qposadr[0] for n in names])
    vadr = np.array([model.joint(n).dofadr[0] for n in names])
    lo, hi = model.jnt_range[[model.joint(n).id for n in names]].T
    site = model.site(tcp_site).id
    data = mujoco.MjData(model)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    goal_rot = panda_spec.INSERTION_ROTATION
    q = np.asarray(seed, dtype=float).copy()
    for _ in range(500):
        data.qpos[qadr] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        rot = data.site_xmat[site].reshape(3, 3)
        turn = 0.5 * sum(np.cross(rot[:, k], goal_rot[:, k]) for k in range(3))
        err = np.concatenate([tcp - data.site_xpos[site], turn])
        if np.linalg.norm(err[:3]) < tolerance and np.linalg.norm(err[3:]) < 10 * tolerance:
            return q
        mujoco.mj_jacSite(model, data, jacp, jacr, site)
        jac = np.vstack([jacp[:, vadr], jacr[:, vadr]])
        q = np.clip(q + jac.T @ np.linalg.solve(jac @ jac.T + 1e-6 * np.eye(6), err), lo, hi)
    raise TaskFileError(f"no joint configuration puts the start's TCP at {np.round(tcp, 3).tolist()} m with the hand "
                        f"pointing down (left {np.linalg.norm(err[:3]) * 1e3:.1f} mm, "
                        f"{np.rad2deg(np.linalg.norm(err[3:])):.1f} deg off): the start is out of the arm's reach")


def _block_scene(plane: str) -> Scene:
    """The 2-D block task. ``plane="vertical"``: gravity along -z (the insertion direction);
    ``"horizontal"``: the x-z plane of motion lies flat, so gravity (along -y) is carried by the
    slide joints and does not act in the plane."""
    if plane not in ("vertical", "horizontal"):
        raise ValueError(f"plane must be 'vertical' or 'horizontal', got {plane!r}")
    spec = mujoco.MjSpec()
    spec.modelname = f"block_{plane}"
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    if plane == "horizontal":
        spec.option.gravity = [0.0, -9.81, 0.0]
    center = np.array([0.0, 0.0, SLOT_TOP])
    _add_lights_and_table(spec, center)
    slot = spec.worldbody.add_body()
    slot.name = "slot"
    half_depth = 0.5 * SLOT_DEPTH
    zc = SLOT_TOP - half_depth
    wall_x = 0.5 * SLOT_WIDTH + SLOT_WALL_HALF_LENGTH
    _box(slot, "slot_wall_left", (SLOT_WALL_HALF_LENGTH, 0.06, half_depth), (-wall_x, 0.0, zc), FIXTURE_RGBA)
    _box(slot, "slot_wall_right", (SLOT_WALL_HALF_LENGTH, 0.06, half_depth), (wall_x, 0.0, zc), FIXTURE_RGBA)
    bottom_top = SLOT_TOP - SLOT_DEPTH
    _box(slot, "slot_bottom", (0.5 * SLOT_WIDTH + 2 * SLOT_WALL_HALF_LENGTH, 0.06, 0.5 * bottom_top),
         (0.0, 0.0, 0.5 * bottom_top), PIN_RGBA)

    block = spec.worldbody.add_body()
    block.name = "block"
    block.pos = [0.0, 0.0, bottom_top + 0.5 * BLOCK_SIZE]  # q = 0: fully inserted
    names = ("block_x", "block_z")
    for name, axis, rng in zip(names, ([1.0, 0, 0], [0, 0, 1.0]), BLOCK_RANGE, strict=True):
        joint = block.add_joint()
        joint.name = name
        joint.type = mujoco.mjtJoint.mjJNT_SLIDE
        joint.axis = axis
        joint.range = list(rng)
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        act = spec.add_actuator()
        act.name = f"{name}_force"
        act.target = name
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.gainprm[0] = 1.0
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = [-BLOCK_FORCE_LIMIT, BLOCK_FORCE_LIMIT]
    geom = block.add_geom()
    geom.name = "block_box"
    geom.type = mujoco.mjtGeom.mjGEOM_BOX
    geom.size = [0.5 * BLOCK_SIZE] * 3
    geom.rgba = BLOCK_RGBA
    geom.contype = CONTACT_MOVING
    geom.conaffinity = 0
    contact_params(geom)
    block.explicitinertial = True
    block.mass = BLOCK_MASS
    block.inertia = [BLOCK_MASS * BLOCK_SIZE**2 / 6.0] * 3
    site = block.add_site()
    site.name = "block_tcp"
    site.pos = [0.0, 0.0, -0.5 * BLOCK_SIZE]
    site.size = [0.004] * 3
    site.rgba = [1.0, 1.0, 0.2, 1.0]
    _add_contact_sensor(spec, "block")
    model = spec.compile()
    return Scene(
        task="block",
        model=model,
        joint_names=names,
        actuator_names=tuple(f"{n}_force" for n in names),
        tcp_site="block_tcp",
        held_body="block",
        fixture_body="slot",
        q_mean=BLOCK_START_MEAN.copy(),
        goal_position=np.array([0.0, 0.0, bottom_top]),
        insertion_top=SLOT_TOP,
        insertion_axis_xy=np.zeros(2),
        lateral_tolerance=0.5 * SLOT_WIDTH,
        success_depth=0.025,
        kind="block",
        camera={"lookat": np.array([0.03, 0.0, 0.12]), "distance": 0.55, "azimuth": 75.0, "elevation": -18.0},
    )


def build_scene(task: str | TaskSpec, *, plane: str = "vertical") -> Scene:
    """Compile the scene of ``task``: a task file (a built-in name such as ``gear``, a path, or a loaded
    ``TaskSpec``), ``block`` or ``free``; ``plane`` applies to the block task. Raises ``ValueError``
    (``TaskFileError``) for an unknown task or a file that cannot be right, with the reason."""
    if isinstance(task, TaskSpec):
        return _arm_scene(task)
    if task == "block":
        return _block_scene(plane)
    if task == "free":
        return _arm_scene(load_task("gear"), free=True)
    return _arm_scene(load_task(task))


def main(argv: list[str] | None = None) -> int:
    """``python -m sim_bridge_node.scenes TASK``: build a task's scene and print what it holds, or why not."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m sim_bridge_node.scenes", description=main.__doc__)
    ap.add_argument("task", help="a built-in task (gear, peg, gear_clamp, block, free) or the path of a task file")
    args = ap.parse_args(argv)
    try:
        scene = build_scene(args.task)
    except ValueError as e:
        print(f"refused: {e}")
        return 1
    print(f"task {scene.task}: {scene.kind}, {scene.model.nbody} bodies, {scene.model.ngeom} geoms")
    if scene.spec is not None:
        spec = scene.spec
        print(f"  part: {spec.part.text()} (TCP {np.round(scene.held_part.tcp_in_hand, 4).tolist()} m in the hand)")
        print(f"  fixture mouth {np.round(spec.top, 4).tolist()} m, goal (seated TCP) "
              f"{np.round(scene.goal_position, 4).tolist()} m, success at {spec.success_depth * 1e3:g} mm, "
              f"friction {spec.friction:g}")
        print(f"  start TCP {np.round(spec.start_tcp, 4).tolist()} m, joints {np.round(scene.q_mean, 6).tolist()} rad")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
