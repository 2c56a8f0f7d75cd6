"""A task file: the part in the hand, the fixture it goes onto or into, the contact friction, the starts
and what counts as success, as a user measures them on their bench. ROS-free.

A task is named by a built-in name (``gear``, ``peg``, ``gear_clamp``: the files in ``config/tasks/``)
or by the path of a YAML file written in the same form (``config/tasks/README.md`` lists every key).
Every consumer builds from the loaded ``TaskSpec``: the simulated scene, the controller's held-part
model, the learner's goal and success, the Franka cell. A file that cannot be right (a bore smaller
than the shaft, a fixture out of the arm's reach, a start inside the fixture, an unknown key) is
refused when it is loaded, with the reason.

Units: metres, kilograms; positions in the robot's base frame (x forward, z up).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from nf_core import panda_spec

PART_KINDS = ("gear", "peg")
HELD_PART_HELP = "gear | peg | none | '<gear|peg> key=value ...' (a task file's part, Part.text)"
BUILTIN_TASK_DIR = Path(__file__).resolve().parents[2] / "config" / "tasks"  # the source tree's
# the hand's fingertips: the gear's top face sits here, the peg is held 10 mm below its top
FINGERTIP_IN_HAND = float(panda_spec.GEAR_COM_IN_HAND[2] - 0.5 * panda_spec.GEAR_DEPTH)  # m
PEG_GRIP = float(FINGERTIP_IN_HAND - panda_spec.PEG_TOP_IN_HAND)  # m of the peg above the fingertips
START_CLEARANCE = 0.005  # m: a start's TCP at least this far above the fixture's top


class TaskFileError(ValueError):
    """A task file that cannot be loaded or cannot be right; the message names the key and the reason."""


@dataclass(frozen=True)
class Part:
    """The part the hand holds. gear: a ring (bore_radius, outer_radius, thickness) whose top face sits
    at the fingertips; peg: a solid rod (radius, length) held with ``PEG_GRIP`` m above the fingertips."""

    kind: str = "gear"
    mass: float = panda_spec.GEAR_MASS  # kg
    bore_radius: float = panda_spec.GEAR_BORE_RADIUS  # m (gear)
    outer_radius: float = panda_spec.GEAR_OUTER_RADIUS  # m (gear)
    thickness: float = panda_spec.GEAR_DEPTH  # m (gear, along the approach axis)
    radius: float = 0.0  # m (peg)
    length: float = 0.0  # m (peg)

    def inertia(self) -> panda_spec.HeldPartInertia:
        """Mass, centre of mass, inertia and TCP in the hand frame (the controller's and the scene's part).
        The TCP is the centre of the part's leading face (the bore mouth; the peg's tip)."""
        for name, builtin in BUILTIN_PARTS.items():
            if self == builtin:
                return panda_spec.HELD_PARTS[name]
        if self.kind == "peg":
            top = FINGERTIP_IN_HAND - PEG_GRIP
            m, r, h = self.mass, self.radius, self.length
            inertia = np.diag([m * (3.0 * r**2 + h**2) / 12.0] * 2 + [0.5 * m * r**2])
            return panda_spec.HeldPartInertia(m, np.array([0.0, 0.0, top + 0.5 * h]), inertia,
                                              np.array([0.0, 0.0, top + h]), "peg", "peg", panda_spec.PEG_TCP_FRAME,
                                              self.text())
        m, r1, r2, h = self.mass, self.bore_radius, self.outer_radius, self.thickness
        ixx = m * (3.0 * (r1**2 + r2**2) + h**2) / 12.0
        inertia = np.diag([ixx, ixx, 0.5 * m * (r1**2 + r2**2)])
        return panda_spec.HeldPartInertia(m, np.array([0.0, 0.0, FINGERTIP_IN_HAND + 0.5 * h]), inertia,
                                          np.array([0.0, 0.0, FINGERTIP_IN_HAND + h]), "gear", "gear",
                                          panda_spec.TCP_FRAME, self.text())

    def text(self) -> str:
        """The part as one line (``held_part`` of a policy's law and of the nodes): the built-in name when
        it is the built-in part, else its kind and sizes, e.g. ``gear bore_radius=0.0175 ... mass=0.12``."""
        for name, builtin in BUILTIN_PARTS.items():
            if self == builtin:
                return name
        keys = ("bore_radius", "outer_radius", "thickness") if self.kind == "gear" else ("radius", "length")
        return " ".join([self.kind] + [f"{k}={getattr(self, k):.6g}" for k in keys] + [f"mass={self.mass:.6g}"])


BUILTIN_PARTS = {
    "gear": Part(),
    "peg": Part(kind="peg", mass=panda_spec.PEG_MASS, bore_radius=0.0, outer_radius=0.0, thickness=0.0,
                radius=panda_spec.PEG_RADIUS, length=panda_spec.PEG_LENGTH),
}


def held_part_inertia(text: str) -> panda_spec.HeldPartInertia | None:
    """The controller's model of a ``held_part`` text (``part_from_text``); None for the bare hand."""
    part = part_from_text(text)
    return None if part is None else part.inertia()


def part_from_text(text: str) -> Part | None:
    """The part of a ``held_part`` text: ``gear``, ``peg``, ``none`` (None: the bare hand) or the one-line
    form of ``Part.text``. Raises ``TaskFileError`` naming what is wrong."""
    text = str(text).strip()
    if text == "none":
        return None
    if text in BUILTIN_PARTS:
        return BUILTIN_PARTS[text]
    kind, *pairs = text.split() or [""]
    if kind not in PART_KINDS or not pairs:
        raise TaskFileError(f"held_part must be one of {(*BUILTIN_PARTS, 'none')} or '<gear|peg> key=value ...', "
                            f"got {text!r}")
    values: dict[str, object] = {"kind": kind}
    if kind == "peg":
        values.update(bore_radius=0.0, outer_radius=0.0, thickness=0.0)
    for pair in pairs:
        key, _, value = pair.partition("=")
        values[key] = value
    return _part(values, "held_part")


@dataclass(frozen=True)
class Fixture:
    """What the part goes onto (a stepped shaft: the gear) or into (a square hole: the peg), standing on
    the table. ``position`` is the insertion axis (x, y) and the height of the shaft's top face or of
    the hole's mouth (z)."""

    position: tuple[float, float, float] = (0.5, 0.0, 0.09)  # m, base frame
    shaft_radius: float = 0.014  # m (gear)
    shaft_length: float = panda_spec.GEAR_DEPTH  # m, pin above the shoulder: the deepest the part goes (gear)
    shoulder_radius: float = 0.022  # m, the part seats on it (gear)
    hole_half_width: float = 0.0125  # m (peg)
    hole_depth: float = 0.020  # m (peg)


@dataclass(frozen=True)
class Clamp:
    """An obstacle between the start and the fixture: a box from the table up to ``top`` across the
    approach (centred on the fixture's y)."""

    center_x: float  # m
    half_thickness: float  # m (x)
    half_length: float  # m (y)
    top: float  # m, z of its top face


@dataclass(frozen=True)
class Starts:
    """Where episodes start. ``tcp``: the nominal TCP position (None: ``height`` above the fixture's top
    on its axis); the nominal joints come from it by inverse kinematics, or are given (``joints``).
    Starts are drawn around them with ``joint_std`` (rad, per joint; None: the environment's default),
    and, with ``region``, redrawn until the TCP lies in that box."""

    height: float = 0.20  # m above the fixture's top
    tcp: tuple[float, float, float] | None = None  # m, base frame
    joints: tuple[float, ...] | None = None  # rad, 7 values
    joint_std: float | None = None  # rad
    region: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # m, [lo, hi]


TASK_STREAM = 31  # second word of a draw's seed: the task randomisation's own random stream


@dataclass(frozen=True)
class TaskDraw:
    """One episode's variation of the cell: what the simulator changes, and what the controller is not told."""

    fixture_offset: np.ndarray  # m (x, y, z), added to the fixture's position
    friction: float  # sliding friction coefficient of every contact
    part_mass: float  # kg (the part's inertia scales with it)


@dataclass(frozen=True)
class Randomise:
    """Per-episode variation of the cell, drawn from the episode's start seed (uniform): the fixture's
    position error (half-ranges, m), the contact friction and the part's mass (ranges; None: the file's)."""

    fixture_position: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, +- per axis
    friction: tuple[float, float] | None = None
    part_mass: tuple[float, float] | None = None  # kg

    @property
    def enabled(self) -> bool:
        """Whether any episode differs from the file's nominal cell."""
        return any(self.fixture_position) or self.friction is not None or self.part_mass is not None

    def draw(self, seed: int | None, friction: float, mass: float) -> TaskDraw:
        """The variation of the episode with start seed ``seed`` (None or < 0: the nominal cell), around the
        file's ``friction`` and ``mass``; from ``default_rng([seed, TASK_STREAM])``."""
        if seed is None or seed < 0:
            return TaskDraw(np.zeros(3), friction, mass)
        rng = np.random.default_rng([int(seed), TASK_STREAM])
        half = np.asarray(self.fixture_position, dtype=float)
        offset = rng.uniform(-half, half)
        mu = rng.uniform(*self.friction) if self.friction is not None else friction
        m = rng.uniform(*self.part_mass) if self.part_mass is not None else mass
        return TaskDraw(offset, float(mu), float(m))


@dataclass(frozen=True)
class TaskSpec:
    """One task file, loaded and checked."""

    name: str
    part: Part = field(default_factory=Part)
    fixture: Fixture = field(default_factory=Fixture)
    friction: float = 0.4  # sliding friction coefficient of every contact
    success_depth: float = 0.016  # m inserted that counts as success
    start: Starts = field(default_factory=Starts)
    clamp: Clamp | None = None
    randomise: Randomise = field(default_factory=Randomise)
    source: str = ""  # the file it was loaded from

    @property
    def kind(self) -> str:
        """``gear`` (onto a shaft) or ``peg`` (into a hole)."""
        return self.part.kind

    @property
    def top(self) -> np.ndarray:
        """The fixture's mouth (m, base frame): the shaft's top face or the hole's, on the axis."""
        return np.asarray(self.fixture.position, dtype=float)

    @property
    def depth(self) -> float:
        """How far the part can go in (m): the pin's length above the shoulder, or the hole's depth."""
        return self.fixture.hole_depth if self.kind == "peg" else self.fixture.shaft_length

    @property
    def goal_position(self) -> np.ndarray:
        """The TCP at full insertion (m): the seated pose, the controller's x_ref."""
        return self.top - np.array([0.0, 0.0, self.depth])

    @property
    def start_tcp(self) -> np.ndarray:
        """The nominal start TCP (m)."""
        if self.start.tcp is not None:
            return np.asarray(self.start.tcp, dtype=float)
        return self.top + np.array([0.0, 0.0, self.start.height])

    @property
    def lateral_tolerance(self) -> float:
        """The TCP this close to the axis (m) counts as in the opening: the bore's radius, or the hole's half width."""
        return self.fixture.hole_half_width if self.kind == "peg" else self.part.bore_radius


# ---------------------------------------------------------------------------------------------- loading
def task_path(task: str | os.PathLike) -> Path:
    """The file of a task: a built-in name (``gear``) or a path to a YAML file. Raises ``TaskFileError``."""
    text = str(task)
    if text.endswith((".yaml", ".yml")) or os.sep in text:
        path = Path(text).expanduser()
        if not path.is_file():
            raise TaskFileError(f"task file {text!r} not found")
        return path
    for folder in builtin_task_dirs():
        path = folder / f"{text}.yaml"
        if path.is_file():
            return path
    raise TaskFileError(f"unknown task {text!r}: give a built-in task ({', '.join(builtin_tasks())}) or the path "
                        f"of a task file (config/tasks/README.md)")


def builtin_task_dirs() -> list[Path]:
    """Where the built-in task files are: the source tree's config/tasks, then each installed
    share/nf_bringup/config/tasks on ``AMENT_PREFIX_PATH``."""
    dirs = [BUILTIN_TASK_DIR]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            dirs.append(Path(prefix) / "share" / "nf_bringup" / "config" / "tasks")
    return [d for d in dirs if d.is_dir()]


def builtin_tasks() -> list[str]:
    """Names of the built-in task files."""
    names = {p.stem for d in builtin_task_dirs() for p in d.glob("*.yaml")}
    return sorted(names)


def is_task_file(task: str | os.PathLike) -> bool:
    """True if ``task`` names a task file (built-in or a path); False for the built-in scenes without one
    (``block``, ``free``) and anything unknown."""
    try:
        task_path(task)
    except TaskFileError:
        return False
    return True


def load_task(task: str | os.PathLike) -> TaskSpec:
    """Load and check a task file (a built-in name or a path). Raises ``TaskFileError`` with the reason."""
    import yaml

    path = task_path(task)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise TaskFileError(f"{path}: not valid YAML: {e}") from None
    name = path.stem if str(task) == path.stem else str(path)
    return task_from_dict(data or {}, name=name, source=str(path))


def task_from_dict(data: dict, name: str = "task", source: str = "") -> TaskSpec:
    """A ``TaskSpec`` from a task file's contents, checked (``check_task``)."""
    where = source or name
    if not isinstance(data, dict):
        raise TaskFileError(f"{where}: a task file is a mapping of keys (part, fixture, ...), "
                            f"got {type(data).__name__}")
    _known(data, ("part", "fixture", "friction", "success_depth", "start", "clamp", "randomise"), where)
    part = _part(dict(data.get("part") or {}), f"{where}: part")
    fx = dict(data.get("fixture") or {})
    if part.kind == "peg":
        fx.setdefault("shaft_radius", 0.0)
        fx.setdefault("shaft_length", 0.0)
        fx.setdefault("shoulder_radius", 0.0)
    else:
        fx.setdefault("hole_half_width", 0.0)
        fx.setdefault("hole_depth", 0.0)
    fixture = _build(Fixture, fx, f"{where}: fixture", vectors={"position": 3})
    start = _build(Starts, dict(data.get("start") or {}), f"{where}: start",
                   vectors={"tcp": 3, "joints": 7, "region": (2, 3)})
    clamp = _build(Clamp, dict(data["clamp"]), f"{where}: clamp") if data.get("clamp") else None
    randomise = _build(Randomise, dict(data.get("randomise") or {}), f"{where}: randomise",
                       vectors={"fixture_position": 3, "friction": 2, "part_mass": 2})
    spec = TaskSpec(name=name, part=part, fixture=fixture,
                    friction=_number(data.get("friction", 0.4), f"{where}: friction"),
                    success_depth=_number(data.get("success_depth", 0.016), f"{where}: success_depth"),
                    start=start, clamp=clamp, randomise=randomise, source=source)
    check_task(spec)
    return spec


def _known(data: dict, keys: tuple[str, ...], where: str) -> None:
    unknown = sorted(set(data) - set(keys))
    if unknown:
        raise TaskFileError(f"{where}: unknown key(s) {unknown}; the keys are {list(keys)}")


def _number(value: object, where: str) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TaskFileError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(x):
        raise TaskFileError(f"{where}: expected a finite number, got {value!r}")
    return x


def _part(values: dict, where: str) -> Part:
    kind = str(values.get("kind", "gear"))
    if kind not in PART_KINDS:
        raise TaskFileError(f"{where}: kind must be one of {PART_KINDS}, got {kind!r}")
    if kind == "peg":
        values = {"bore_radius": 0.0, "outer_radius": 0.0, "thickness": 0.0, "mass": None, **values}
        for key in ("bore_radius", "outer_radius", "thickness"):
            if values[key]:
                raise TaskFileError(f"{where}: {key} is a gear's; a peg has radius and length")
        if values.get("mass") is None:  # aluminium by default
            r, h = (_number(values.get(k, d), f"{where}: {k}") for k, d in (("radius", 0.0), ("length", 0.0)))
            values["mass"] = 2700.0 * math.pi * r**2 * h
    return _build(Part, values, where)


def _build(cls: type, values: dict, where: str, vectors: dict | None = None):
    vectors = vectors or {}
    names = [f.name for f in fields(cls)]
    _known(values, tuple(names), where)
    out = {}
    for key, value in values.items():
        if key == "kind":
            out[key] = str(value)
        elif value is None:
            out[key] = None
        elif key in vectors:
            shape = vectors[key] if isinstance(vectors[key], tuple) else (vectors[key],)
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise TaskFileError(f"{where}: {key} must be {shape} numbers, got {value!r}") from None
            if arr.shape != shape or not np.all(np.isfinite(arr)):
                raise TaskFileError(f"{where}: {key} must be {'x'.join(map(str, shape))} finite numbers, got {value!r}")
            out[key] = tuple(map(tuple, arr.tolist())) if arr.ndim == 2 else tuple(arr.tolist())
        else:
            out[key] = _number(value, f"{where}: {key}")
    return cls(**out)


# ---------------------------------------------------------------------------------------------- checks
def check_task(spec: TaskSpec) -> None:
    """Refuse a task that cannot be right: sizes that do not fit, a fixture out of reach, a start inside
    the fixture or not reachable. Raises ``TaskFileError`` with the reason."""
    where, p, f = spec.source or spec.name, spec.part, spec.fixture
    if p.kind == "gear":
        positive = {"part: bore_radius": p.bore_radius, "part: outer_radius": p.outer_radius,
                    "part: thickness": p.thickness, "fixture: shaft_radius": f.shaft_radius,
                    "fixture: shaft_length": f.shaft_length, "fixture: shoulder_radius": f.shoulder_radius}
    else:
        positive = {"part: radius": p.radius, "part: length": p.length,
                    "fixture: hole_half_width": f.hole_half_width, "fixture: hole_depth": f.hole_depth}
    positive.update({"part: mass": p.mass, "friction": spec.friction, "success_depth": spec.success_depth})
    for key, value in positive.items():
        if not value > 0.0:
            raise TaskFileError(f"{where}: {key} must be > 0, got {value:g}")
    if spec.friction > 2.0:
        raise TaskFileError(f"{where}: friction {spec.friction:g} is not a sliding friction coefficient (0 < mu <= 2)")
    if p.kind == "gear":
        if p.bore_radius <= f.shaft_radius:
            raise TaskFileError(f"{where}: the bore (radius {p.bore_radius * 1e3:g} mm) is not larger than the shaft "
                                f"(radius {f.shaft_radius * 1e3:g} mm): the gear cannot go on")
        if p.outer_radius <= p.bore_radius:
            raise TaskFileError(f"{where}: the gear's outer radius {p.outer_radius * 1e3:g} mm is not larger than "
                                f"its bore's {p.bore_radius * 1e3:g} mm")
        if f.shoulder_radius <= p.bore_radius:
            raise TaskFileError(f"{where}: the shoulder (radius {f.shoulder_radius * 1e3:g} mm) is not larger than "
                                f"the bore ({p.bore_radius * 1e3:g} mm): nothing for the gear to seat on")
    else:
        if p.radius >= f.hole_half_width:
            raise TaskFileError(f"{where}: the peg (radius {p.radius * 1e3:g} mm) does not fit the hole (half width "
                                f"{f.hole_half_width * 1e3:g} mm)")
        if p.length <= f.hole_depth:
            raise TaskFileError(f"{where}: the peg ({p.length * 1e3:g} mm) is not longer than the hole is deep "
                                f"({f.hole_depth * 1e3:g} mm): the hand would hit the block")
    if spec.success_depth > spec.depth + 1e-12:
        raise TaskFileError(f"{where}: success_depth {spec.success_depth * 1e3:g} mm is deeper than the part can go "
                            f"({spec.depth * 1e3:g} mm)")
    top = spec.top
    if top[2] - spec.depth < 0.0:
        raise TaskFileError(f"{where}: fixture: position z {top[2]:g} m puts the seated part below the table (z = 0)")
    if np.linalg.norm(top) > panda_spec.MAX_REACH or np.linalg.norm(spec.start_tcp) > panda_spec.MAX_REACH:
        raise TaskFileError(f"{where}: the fixture at {np.round(top, 3).tolist()} m or the start at "
                            f"{np.round(spec.start_tcp, 3).tolist()} m is beyond the arm's reach "
                            f"({panda_spec.MAX_REACH:g} m from the base)")
    if np.hypot(*top[:2]) < 0.25:
        raise TaskFileError(f"{where}: the fixture at {np.round(top, 3).tolist()} m is inside the arm's own "
                            f"footprint (closer than 0.25 m to the base's axis)")
    s = spec.start_tcp
    if s[2] < top[2] + START_CLEARANCE:
        raise TaskFileError(f"{where}: the start (TCP z {s[2]:g} m) is not above the fixture's top ({top[2]:g} m "
                            f"+ {START_CLEARANCE * 1e3:g} mm): it would start inside the fixture")
    r = spec.randomise
    if any(not 0.0 <= h <= 0.02 for h in r.fixture_position):
        raise TaskFileError(f"{where}: randomise: fixture_position half-ranges must be in [0, 0.02] m, "
                            f"got {list(r.fixture_position)}")
    for key, rng, lo, hi in (("friction", r.friction, 0.0, 2.0), ("part_mass", r.part_mass, 0.0, 100.0)):
        if rng is not None and not lo < rng[0] <= rng[1] <= hi:
            raise TaskFileError(f"{where}: randomise: {key} must be a range [lo, hi] with {lo:g} < lo <= hi <= {hi:g}, "
                                f"got {list(rng)}")
    if spec.start.joint_std is not None and not 0.0 <= spec.start.joint_std <= 0.5:
        raise TaskFileError(f"{where}: start: joint_std must be in [0, 0.5] rad, got {spec.start.joint_std:g}")


def scripted_waypoints(task: TaskSpec, start: np.ndarray) -> list[np.ndarray]:
    """What a person would show from TCP ``start`` (m): with a clamp, towards it at the start's height
    until the part's rim is 3 cm from its face, up while closing to 0.5 cm, over it 12 cm above its top
    to above the fixture, and down onto it; without one, to 5 cm above the fixture and down."""
    goal = task.goal_position
    if task.clamp is None:
        return [np.array([goal[0], goal[1], task.top[2] + 0.05]), goal]
    rim = task.part.outer_radius if task.kind != "peg" else task.part.radius
    face = task.clamp.center_x + task.clamp.half_thickness  # the side the starts are on (+x)
    over = task.clamp.top + 0.12
    return [np.array([face + rim + 0.03, start[1], start[2]]),
            np.array([face + rim + 0.005, start[1], over]),
            np.array([goal[0], goal[1], over - 0.03]),
            goal]
