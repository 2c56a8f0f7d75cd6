"""MuJoCo scenes for the three tasks, plus a free-space scene, built with ``mujoco.MjSpec``.

World frame: the Panda's base (``panda_link0``) at the origin on the table plane z = 0, x forward.

- ``gear``: a stepped steel shaft at ``FIXTURE_XY`` on the table: a 100 x 100 x 40 mm base block,
  a 44 mm shoulder 30 mm high, then the 28 mm pin, ``GEAR_DEPTH`` (20 mm) long, so the pin top is
  at ``FIXTURE_TOP`` and the gear seats on the shoulder at full depth.
- ``peg``: a block with a 25 mm square hole, 20 mm deep, top face at ``FIXTURE_TOP``, made of a
  base and four wall boxes; the arm holds the 23 mm peg instead of the gear.
- ``block``: no arm. A 50 mm, 1 kg cube on two slide joints (x and z) with force motors, above a
  slot 52 mm wide (1 mm per side) and 50 mm deep cut between two wall boxes.
- ``gear_clamp``: the ``gear`` scene plus a clamp (a steel jaw, ``CLAMP_*``) standing between the
  gear's start and the shaft; the gear starts low behind it (``Q_MEAN_GEAR_CLAMP``, TCP below the
  clamp's top), so it has to be lifted over the clamp and lowered onto the shaft. Every path along
  which each coordinate moves monotonically to the goal runs into the clamp (``gear_clamp.yaml``).
- ``free``: the Panda with the gear, the table plane and lights, nothing else.

Contacts: every solid geom of a scene uses ``CONTACT_SOLREF``/``CONTACT_SOLIMP`` and friction
``CONTACT_FRICTION`` (steel on aluminium), which keeps resting penetration well below 0.5 mm
under the forces the arm can push with; convex pairs yield one contact each (multi-point
convex collision off, see ``_add_lights_and_table``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from nf_core import panda_spec
from sim_bridge_node.held_parts import HeldPart, add_gear, add_peg
from sim_bridge_node.panda_model import CONTACT_MOVING, TIMESTEP, load_panda_spec

TASKS = ("gear", "peg", "block", "free", "gear_clamp")

# Contact model (all solid geoms): stiff, critically damped soft contacts.
CONTACT_SOLREF = np.array([0.004, 1.0])  # time constant (>= 2 time steps), damping ratio
CONTACT_SOLIMP = np.array([0.95, 0.99, 0.0005, 0.5, 2.0])
CONTACT_FRICTION = np.array([0.4, 0.005, 0.0001])  # sliding, torsional, rolling
CONTACT_CONDIM = 3

# Fixture (shaft or hole) placement and geometry.
FIXTURE_XY = np.array([0.5, 0.0])  # m, fixture axis in the table plane
FIXTURE_TOP = 0.09  # m, z of the shaft's top face / the hole's mouth
FIXTURE_BASE_HALF = 0.05  # m, half side of the square base block
SHAFT_RADIUS = 0.014  # m (28 mm shaft)
SHAFT_LENGTH = panda_spec.GEAR_DEPTH  # m, pin length above the shoulder = full insertion depth
SHOULDER_RADIUS = 0.022  # m, the gear seats on it (bore 15 mm < 22 mm < outer 30 mm)
HOLE_HALF_WIDTH = 0.0125  # m (25 mm square hole)
HOLE_DEPTH = 0.020  # m
HOLE_BLOCK_HALF = 0.04  # m, half side of the hole block

# Start poses (hand pointing straight down, TCP 0.20 m above the fixture top, on its axis),
# solved once by inverse kinematics from the Panda's "ready" posture; see tests/test_sim_scenes.py.
START_HEIGHT = 0.20  # m above FIXTURE_TOP
Q_MEAN_GEAR = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])
Q_MEAN_PEG = np.array([0.0, -0.150447, 0.0, -2.209835, 0.0, 2.059387, 0.785398])

# gear_clamp: a clamp jaw (box) across the approach, between the shaft's base block (x 0.45-0.55) and
# the start, which lies further from the robot. It spans the whole y range of the starts and rises 8 cm
# above the start's TCP, so the gear must be lifted over it: the straight line, and every path that
# moves each coordinate monotonically from the start to the goal, hits it. It stands 5 cm off the base
# block, so the gear can be lowered behind it and then approach the shaft as on the plain gear task.
CLAMP_CENTER_X = 0.61  # m: the seated gear's rim (r = 30 mm) clears it by 7 cm
CLAMP_HALF_THICKNESS = 0.01  # m (x)
CLAMP_HALF_LENGTH = 0.10  # m (y), centred on the shaft axis
CLAMP_TOP = 0.20  # m, z of its top face (11 cm above the shaft top, 8 cm above the start's TCP)
START_TCP_GEAR_CLAMP = np.array([0.71, 0.0, 0.12])  # m: the gear's rim 6 cm behind the clamp, TCP 8 cm below its top
START_STD_GEAR_CLAMP = 0.05  # rad per joint (TCP std ~1.5, 3, 1 cm in x, y, z); starts outside the region are redrawn
# TCP box [lo, hi] of a sampled start: behind the clamp (the gear's rim >= 2 cm off it), below its top
START_REGION_GEAR_CLAMP = np.array([
    [CLAMP_CENTER_X + CLAMP_HALF_THICKNESS + panda_spec.GEAR_OUTER_RADIUS + 0.02, -0.06, FIXTURE_TOP + 0.01],
    [0.76, 0.06, FIXTURE_TOP + 0.05],
])
# START_TCP_GEAR_CLAMP with the hand pointing down (as Q_MEAN_GEAR), by damped least squares from
# Q_MEAN_GEAR (tests/test_gear_clamp.py checks the TCP)
Q_MEAN_GEAR_CLAMP = np.array([0.0, 0.705731, 0.0, -1.523225, 0.0, 2.228955, 0.785398])

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


def add_shaft(spec: mujoco.MjSpec) -> None:
    """Stepped shaft: base block, shoulder, 28 mm pin (convex pieces: one box, two cylinders), its
    top face at ``FIXTURE_TOP`` over ``FIXTURE_XY`` (``nf_bringup.testing.franky`` moves a copy)."""
    body = spec.worldbody.add_body()
    body.name = "shaft"
    body.pos = [FIXTURE_XY[0], FIXTURE_XY[1], 0.0]
    pin_bottom = FIXTURE_TOP - SHAFT_LENGTH
    base_top = 0.04
    half = FIXTURE_BASE_HALF
    _box(body, "shaft_base", (half, half, 0.5 * base_top), (0.0, 0.0, 0.5 * base_top), FIXTURE_RGBA)
    _cylinder(body, "shaft_shoulder", SHOULDER_RADIUS, base_top, pin_bottom, PIN_RGBA)
    _cylinder(body, "shaft_pin", SHAFT_RADIUS, pin_bottom, FIXTURE_TOP, PIN_RGBA)


def _add_hole(spec: mujoco.MjSpec) -> None:
    """Block with a 25 mm square hole, 20 mm deep: a base and four wall boxes."""
    body = spec.worldbody.add_body()
    body.name = "hole"
    body.pos = [FIXTURE_XY[0], FIXTURE_XY[1], 0.0]
    bottom = FIXTURE_TOP - HOLE_DEPTH
    a, b = HOLE_HALF_WIDTH, HOLE_BLOCK_HALF
    _box(body, "hole_base", (b, b, 0.5 * bottom), (0.0, 0.0, 0.5 * bottom), FIXTURE_RGBA)
    zc, hz = 0.5 * (bottom + FIXTURE_TOP), 0.5 * HOLE_DEPTH
    wall = 0.5 * (b - a)
    _box(body, "hole_wall_px", (wall, b, hz), (a + wall, 0.0, zc), PIN_RGBA)
    _box(body, "hole_wall_nx", (wall, b, hz), (-a - wall, 0.0, zc), PIN_RGBA)
    _box(body, "hole_wall_py", (a, wall, hz), (0.0, a + wall, zc), PIN_RGBA)
    _box(body, "hole_wall_ny", (a, wall, hz), (0.0, -a - wall, zc), PIN_RGBA)


def add_clamp(spec: mujoco.MjSpec) -> None:
    """The clamp jaw of ``gear_clamp``: one box from the table up to ``CLAMP_TOP`` across the approach."""
    body = spec.worldbody.add_body()
    body.name = "clamp"
    body.pos = [CLAMP_CENTER_X, FIXTURE_XY[1], 0.0]
    _box(body, "clamp_jaw", (CLAMP_HALF_THICKNESS, CLAMP_HALF_LENGTH, 0.5 * CLAMP_TOP), (0.0, 0.0, 0.5 * CLAMP_TOP),
         FIXTURE_RGBA)


def _arm_scene(task: str) -> Scene:
    spec = load_panda_spec()
    hand = spec.body(panda_spec.HAND_FRAME)
    held = add_peg(hand) if task == "peg" else add_gear(hand)
    for geom in spec.body(held.body).geoms:
        if geom.contype:
            contact_params(geom)
    for body in spec.bodies:  # arm links may touch the table and fixtures with the same model
        if body.name.startswith("panda_"):
            for geom in body.geoms:
                contact_params(geom)
    center = np.array([FIXTURE_XY[0], FIXTURE_XY[1], FIXTURE_TOP])
    _add_lights_and_table(spec, center)
    fixture = ""
    if task in ("gear", "gear_clamp"):
        add_shaft(spec)
        fixture = "shaft"
        if task == "gear_clamp":
            add_clamp(spec)
        # The closed fingertip pads reach 9.5 mm into the bore's upper end (they "hold" the gear
        # there); the pin passes between them at full depth instead of stopping on them.
        for finger in ("panda_leftfinger", "panda_rightfinger"):
            exclude = spec.add_exclude()
            exclude.bodyname1 = finger
            exclude.bodyname2 = "shaft"
    elif task == "peg":
        _add_hole(spec)
        fixture = "hole"
    _add_contact_sensor(spec, held.body)
    model = spec.compile()
    q_mean = Q_MEAN_PEG if task == "peg" else Q_MEAN_GEAR
    start_std, start_region = None, None
    if task == "gear_clamp":
        q_mean, start_std, start_region = Q_MEAN_GEAR_CLAMP, START_STD_GEAR_CLAMP, START_REGION_GEAR_CLAMP.copy()
    goal = np.array([FIXTURE_XY[0], FIXTURE_XY[1], FIXTURE_TOP - SHAFT_LENGTH])
    lateral = panda_spec.GEAR_BORE_RADIUS
    if task == "peg":
        goal = np.array([FIXTURE_XY[0], FIXTURE_XY[1], FIXTURE_TOP - HOLE_DEPTH])
        lateral = HOLE_HALF_WIDTH
    camera = {"lookat": center + [0.0, 0.0, 0.03], "distance": 0.45, "azimuth": 145.0, "elevation": -24.0}
    if task == "free":
        camera = {"lookat": np.array([0.25, 0.0, 0.35]), "distance": 1.7, "azimuth": 140.0, "elevation": -20.0}
    return Scene(
        task=task,
        model=model,
        joint_names=panda_spec.JOINT_NAMES,
        actuator_names=tuple(f"{n}_motor" for n in panda_spec.JOINT_NAMES),
        tcp_site=held.tcp_site,
        held_body=held.body,
        fixture_body=fixture,
        q_mean=q_mean.copy(),
        goal_position=goal,
        insertion_top=FIXTURE_TOP,
        insertion_axis_xy=FIXTURE_XY.copy(),
        lateral_tolerance=lateral,
        success_depth=0.016,
        held_part=held,
        start_std=start_std,
        start_region=start_region,
        camera=camera,
    )


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
        camera={"lookat": np.array([0.03, 0.0, 0.12]), "distance": 0.55, "azimuth": 75.0, "elevation": -18.0},
    )


def build_scene(task: str, *, plane: str = "vertical") -> Scene:
    """Compile the scene for ``task`` (one of ``TASKS``); ``plane`` applies to the block task."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
    if task == "block":
        return _block_scene(plane)
    return _arm_scene(task)
