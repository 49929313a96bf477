"""Kinematic-tree model as a frozen pytree, and host-side loaders (URDF via Pinocchio).

A :class:`Model` is built once on the host (from a URDF or an existing Pinocchio model),
rejecting what the JAX dynamics do not support with a named error, and is then an ordinary
pytree: its array fields (placements, inertias, axes, limits, gravity) are traced, so they can
be batched or differentiated; its structural fields (joint types, parents, index offsets,
names) are static, so the tree is unrolled at trace time.

Indexing follows Pinocchio: joint 0 is the universe (the world, fixed), joints ``1..n`` are
ordered so that a parent precedes its children, and frame ids are Pinocchio's frame ids. This
lets ids be exchanged with Pinocchio freely in tests and tools.
"""

from __future__ import annotations

import importlib.metadata
import pathlib
import sys
import xml.etree.ElementTree as ElementTree
from typing import Any

import equinox as eqx
import jax
import numpy as np

from rsmooth._xla import device_array

FREE_FLYER = "free_flyer"
SPHERICAL = "spherical"
REVOLUTE = "revolute"
PRISMATIC = "prismatic"
UNIVERSE = "universe"

# Tangent dimension of each supported joint type (the configuration dimension is the same,
# except for the free flyer whose orientation is a quaternion: nq = 7, nv = 6).
JOINT_NV = {UNIVERSE: 0, FREE_FLYER: 6, SPHERICAL: 3, REVOLUTE: 1, PRISMATIC: 1}
JOINT_NQ = {UNIVERSE: 0, FREE_FLYER: 7, SPHERICAL: 4, REVOLUTE: 1, PRISMATIC: 1}

_UNIT_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


class Model(eqx.Module):
    """A kinematic tree of rigid bodies (no contact), as a frozen pytree.

    Joint ``i`` moves body ``i`` relative to body ``parents[i]``; its placement in the parent
    joint frame at zero configuration is ``(joint_placement_rotation[i],
    joint_placement_translation[i])``. Index 0 is the universe (fixed world, no body).

    Supported joints: ``"free_flyer"`` (``q = [x, y, z, qx, qy, qz, qw]``, ``v = [linear,
    angular]`` in the joint frame, as Pinocchio), ``"spherical"`` (a ball joint: ``q = [qx, qy,
    qz, qw]``, ``v`` the angular velocity in the joint frame, as Pinocchio's and MuJoCo's),
    ``"revolute"`` about ``joint_axes[i]``, ``"prismatic"`` along ``joint_axes[i]``.

    Attributes:
        joint_names: name of every joint, ``joint_names[0] == "universe"``.
        joint_types: ``"universe"``, ``"free_flyer"``, ``"spherical"``, ``"revolute"`` or ``"prismatic"``.
        parents: parent joint index of every joint (``parents[0] == 0``).
        idx_q: offset of every joint in the configuration vector.
        idx_v: offset of every joint in the velocity vector.
        frame_names: name of every frame (Pinocchio's frames: bodies, joints, fixed joints...).
        frame_parents: index of the joint every frame is attached to.
        nq: configuration dimension.
        nv: velocity (tangent) dimension.
        joint_axes: unit axis of revolute/prismatic joints in the joint frame, ``(njoints, 3)``
            (zeros for other types).
        joint_placement_rotation: ``(njoints, 3, 3)``.
        joint_placement_translation: ``(njoints, 3)``.
        body_mass: ``(njoints,)``, mass of the body carried by every joint (fixed-joint
            children already merged, as Pinocchio does).
        body_com: ``(njoints, 3)``, centre of mass in the joint frame.
        body_inertia: ``(njoints, 3, 3)``, rotational inertia about the centre of mass, in
            the joint frame's axes.
        frame_placement_rotation: ``(nframes, 3, 3)``, placement of frames in their joint.
        frame_placement_translation: ``(nframes, 3)``.
        lower_position_limit: ``(nq,)``; ``-inf`` where unlimited.
        upper_position_limit: ``(nq,)``; ``+inf`` where unlimited. For a spherical joint,
            its entry at the joint's first coordinate is a cone limit: the largest rotation
            angle of the joint (rad, in ``(0, pi]``); its other entries are ``+inf``.
        velocity_limit: ``(nv,)``; ``+inf`` where unlimited.
        effort_limit: ``(nv,)``; ``+inf`` where unlimited.
        armature: ``(nv,)``, rotor inertia added to the diagonal of the mass matrix.
        gravity: ``(3,)``, linear gravity acceleration in the world frame.
    """

    joint_names: tuple[str, ...] = eqx.field(static=True)
    joint_types: tuple[str, ...] = eqx.field(static=True)
    parents: tuple[int, ...] = eqx.field(static=True)
    idx_q: tuple[int, ...] = eqx.field(static=True)
    idx_v: tuple[int, ...] = eqx.field(static=True)
    frame_names: tuple[str, ...] = eqx.field(static=True)
    frame_parents: tuple[int, ...] = eqx.field(static=True)
    nq: int = eqx.field(static=True)
    nv: int = eqx.field(static=True)
    joint_axes: jax.Array
    joint_placement_rotation: jax.Array
    joint_placement_translation: jax.Array
    body_mass: jax.Array
    body_com: jax.Array
    body_inertia: jax.Array
    frame_placement_rotation: jax.Array
    frame_placement_translation: jax.Array
    lower_position_limit: jax.Array
    upper_position_limit: jax.Array
    velocity_limit: jax.Array
    effort_limit: jax.Array
    armature: jax.Array
    gravity: jax.Array

    def __check_init__(self):
        njoints = len(self.joint_names)
        if not (len(self.joint_types) == len(self.parents) == len(self.idx_q) == len(self.idx_v) == njoints):
            raise ValueError("joint_names, joint_types, parents, idx_q and idx_v must have the same length")
        if njoints == 0 or self.joint_types[0] != UNIVERSE:
            raise ValueError("joint 0 must be the universe")
        if len(self.frame_names) != len(self.frame_parents):
            raise ValueError("frame_names and frame_parents must have the same length")
        next_q = next_v = 0
        for i in range(1, njoints):
            kind = self.joint_types[i]
            if kind not in (FREE_FLYER, SPHERICAL, REVOLUTE, PRISMATIC):
                raise ValueError(f"joint {self.joint_names[i]!r} has unsupported type {kind!r}")
            if not 0 <= self.parents[i] < i:
                raise ValueError(f"joint {self.joint_names[i]!r}: parent must precede the joint")
            # The dynamics concatenate per-joint blocks in joint order: offsets must follow it.
            if self.idx_q[i] != next_q or self.idx_v[i] != next_v:
                raise ValueError(f"joint {self.joint_names[i]!r}: configuration offsets not in joint order")
            next_q += JOINT_NQ[kind]
            next_v += JOINT_NV[kind]
        if (next_q, next_v) != (self.nq, self.nv):
            raise ValueError(f"nq, nv = {self.nq}, {self.nv} but the joints add up to {next_q}, {next_v}")
        for f, parent in enumerate(self.frame_parents):
            if not 0 <= parent < njoints:
                raise ValueError(f"frame {self.frame_names[f]!r} is attached to unknown joint {parent}")
        self._check_values()

    def _check_values(self) -> None:
        """Rejects impossible values (non-finite geometry or inertia, negative mass or
        armature) in the fields that are concrete; traced fields are the caller's."""

        def concrete(name):
            value = getattr(self, name)
            return None if isinstance(value, jax.core.Tracer) else np.asarray(value)

        for name in ("joint_axes", "joint_placement_rotation", "joint_placement_translation", "body_com",
                     "body_inertia", "frame_placement_rotation", "frame_placement_translation", "gravity"):
            value = concrete(name)
            if value is not None and not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be finite, got NaN or inf at index {_first_bad(value)}")
        mass = concrete("body_mass")
        if mass is not None:
            for i, m in enumerate(mass):
                if not (np.isfinite(m) and m >= 0):
                    raise ValueError(f"the body of joint {self.joint_names[i]!r} has mass {m}: it must be finite and >= 0")
        armature = concrete("armature")
        if armature is not None and not np.all(np.isfinite(armature) & (armature >= 0)):
            raise ValueError(f"armature must be finite and >= 0, got {armature.tolist()}")
        for name in ("lower_position_limit", "upper_position_limit", "velocity_limit", "effort_limit"):
            value = concrete(name)
            if value is not None and np.any(np.isnan(value)):
                raise ValueError(f"{name} must not be NaN (inf means unlimited), got {value.tolist()}")

    @property
    def njoints(self) -> int:
        """Number of joints, the universe included (as Pinocchio's ``model.njoints``)."""
        return len(self.joint_names)

    @property
    def nframes(self) -> int:
        """Number of frames."""
        return len(self.frame_names)

    def joint_nq(self, joint: int) -> int:
        """Configuration dimension of a joint."""
        return JOINT_NQ[self.joint_types[joint]]

    def joint_nv(self, joint: int) -> int:
        """Velocity dimension of a joint."""
        return JOINT_NV[self.joint_types[joint]]

    def frame_id(self, frame: str | int) -> int:
        """Index of a frame given by name (the first frame so named, as ``pin.getFrameId``).

        Args:
            frame: frame name, or an index (returned after a range check).

        Returns:
            The frame index.

        Raises:
            ValueError: if there is no such frame.
        """
        if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
            if not 0 <= frame < self.nframes:
                raise ValueError(f"frame index {frame} out of range [0, {self.nframes})")
            return int(frame)
        try:
            return self.frame_names.index(frame)
        except ValueError:
            raise ValueError(f"no frame named {frame!r}; frames are {list(self.frame_names)}") from None

    def joint_id(self, joint: str | int) -> int:
        """Index of a joint given by name (or an index, range-checked)."""
        if isinstance(joint, (int, np.integer)) and not isinstance(joint, bool):
            if not 0 <= joint < self.njoints:
                raise ValueError(f"joint index {joint} out of range [0, {self.njoints})")
            return int(joint)
        try:
            return self.joint_names.index(joint)
        except ValueError:
            raise ValueError(f"no joint named {joint!r}; joints are {list(self.joint_names)}") from None

    def support(self, joint: int) -> tuple[int, ...]:
        """Joints from the root to ``joint`` (included), universe excluded, root first."""
        chain = []
        while joint != 0:
            chain.append(joint)
            joint = self.parents[joint]
        return tuple(reversed(chain))


def _first_bad(values: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(~np.isfinite(values))[0])


# Tolerance of the inertia checks: relative to the largest principal moment, plus an absolute
# floor for point masses (zero inertia, whose computed moments are rounding noise ~1e-20).
_INERTIA_RTOL, _INERTIA_ATOL = 1e-6, 1e-12


def _inertia_violation(inertia: np.ndarray) -> str | None:
    """Why a rotational inertia (3, 3) about the centre of mass is not that of a rigid body, or
    None: its principal moments must be >= 0 and satisfy the triangle inequality
    ``I1 + I2 >= I3`` (each principal moment is the sum of two of the three second moments of
    mass ``sum m x_i^2``), within a tolerance."""
    moments = np.linalg.eigvalsh(0.5 * (inertia + inertia.T))  # ascending
    tolerance = _INERTIA_RTOL * float(np.max(np.abs(moments))) + _INERTIA_ATOL
    shown = ", ".join(f"{m:.6g}" for m in moments)
    if not np.allclose(inertia, inertia.T, rtol=_INERTIA_RTOL, atol=_INERTIA_ATOL):
        return "it is not symmetric"
    if moments[0] < -tolerance:
        return f"its principal moments ({shown}) are not all >= 0"
    if moments[0] + moments[1] < moments[2] - tolerance:
        return f"its principal moments ({shown}) violate the triangle inequality I1 + I2 >= I3"
    return None


def _urdf_number(text: str | None, what: str, path: pathlib.Path) -> float:
    try:
        return float(text if text is not None else "0")
    except ValueError:
        raise ValueError(f"{path}: {what} is {text!r}, not a number") from None


def _check_urdf_inertials(root: ElementTree.Element, path: pathlib.Path) -> None:
    """Rejects the links whose mass is negative or not finite, or whose inertia is not finite
    (Pinocchio loads them, and the dynamics then give NaN). A zero mass is legal: URDF files
    use massless links for frames."""
    for link in root.iter("link"):
        name = link.get("name")
        inertial = link.find("inertial")
        if inertial is None:
            continue
        mass_element = inertial.find("mass")
        if mass_element is not None:
            mass = _urdf_number(mass_element.get("value"), f"the mass of link {name!r}", path)
            if not (np.isfinite(mass) and mass >= 0):
                raise ValueError(f"{path}: link {name!r} has mass {mass}: a mass must be finite and >= 0")
        inertia = inertial.find("inertia")
        if inertia is not None:
            for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
                value = _urdf_number(inertia.get(key), f"the inertia {key} of link {name!r}", path)
                if not np.isfinite(value):
                    raise ValueError(f"{path}: link {name!r} has inertia {key} = {value}: it must be finite")
        origin = inertial.find("origin")
        if origin is not None:
            for key in ("xyz", "rpy"):
                for value in (origin.get(key) or "").split():
                    if not np.isfinite(_urdf_number(value, f"the inertial origin {key} of link {name!r}", path)):
                        raise ValueError(f"{path}: link {name!r} has inertial origin {key}={origin.get(key)!r}: it must be finite")


def _check_body_inertias(pin: Any, pin_model: Any, path: pathlib.Path) -> None:
    """Rejects the bodies (a joint's link with the links fixed to it, merged by Pinocchio) whose
    rotational inertia is not that of a rigid body (:func:`_inertia_violation`)."""
    for i in range(1, pin_model.njoints):
        inertia = pin_model.inertias[i]
        problem = _inertia_violation(np.asarray(inertia.inertia, dtype=np.float64))
        if problem is None:
            continue
        links = [str(f.name) for f in pin_model.frames if int(f.parentJoint) == i and f.type == pin.FrameType.BODY]
        body = f"link {links[0]!r}" + (" with the links fixed to it" if len(links) > 1 else "") if links else "body"
        raise ValueError(
            f"{path}: the inertia of the {body}, moved by joint {str(pin_model.names[i])!r}, is not that of a "
            f"rigid body: {problem} (mass {inertia.mass:.6g}); load_urdf(..., check_inertia=False) skips this check"
        )


def _limits_to_inf(values: np.ndarray) -> np.ndarray:
    """Pinocchio marks "no limit" with the largest double; an infinity says it plainly."""
    values = np.array(values, dtype=np.float64)
    huge = np.abs(values) >= 0.5 * np.finfo(np.float64).max
    values[huge] = np.sign(values[huge]) * np.inf
    return values


def _to_jax(values: Any) -> jax.Array:
    return device_array(values)


def _joint_type_and_axis(joint_model: Any, name: str) -> tuple[str, tuple[float, float, float]]:
    shortname = joint_model.shortname()
    if shortname == "JointModelFreeFlyer":
        return FREE_FLYER, (0.0, 0.0, 0.0)
    if shortname == "JointModelSpherical":
        return SPHERICAL, (0.0, 0.0, 0.0)
    for prefix, kind in (("JointModelR", REVOLUTE), ("JointModelP", PRISMATIC)):
        suffix = shortname[len(prefix) :]
        if shortname.startswith(prefix) and suffix in _UNIT_AXES:
            return kind, _UNIT_AXES[suffix]
    if shortname in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
        kind = REVOLUTE if shortname == "JointModelRevoluteUnaligned" else PRISMATIC
        axis = np.asarray(joint_model.extract().axis, dtype=np.float64)
        return kind, tuple(float(a) for a in axis / np.linalg.norm(axis))
    raise ValueError(
        f"joint {name!r} has type {shortname}, which rsmooth.sim does not support "
        "(supported: free-flyer, spherical, revolute and prismatic joints; continuous URDF joints become "
        "unbounded revolute joints in Pinocchio and are not supported either)"
    )


def from_pinocchio(pin_model: Any) -> Model:
    """Freezes a Pinocchio model into a :class:`Model` of JAX arrays.

    Args:
        pin_model: a ``pinocchio.Model``.

    Returns:
        The equivalent model; joint and frame indices are Pinocchio's.

    Raises:
        ValueError: if a joint type is not supported (the error names the joint), or a body
            has a negative or non-finite mass, or a value is not finite.
    """
    njoints = pin_model.njoints
    names = tuple(str(name) for name in pin_model.names)
    types, axes = [UNIVERSE], [(0.0, 0.0, 0.0)]
    for i in range(1, njoints):
        kind, axis = _joint_type_and_axis(pin_model.joints[i], names[i])
        types.append(kind)
        axes.append(axis)
    joints = [pin_model.joints[i] for i in range(njoints)]
    placements = [pin_model.jointPlacements[i] for i in range(njoints)]
    inertias = [pin_model.inertias[i] for i in range(njoints)]
    frames = [pin_model.frames[f] for f in range(pin_model.nframes)]
    gravity = pin_model.gravity
    if np.any(np.asarray(gravity.angular) != 0.0):
        raise ValueError("the model's gravity has a non-zero angular part, which is not supported")
    return Model(
        joint_names=names,
        joint_types=tuple(types),
        parents=tuple(int(p) for p in pin_model.parents),
        idx_q=(0,) + tuple(int(j.idx_q) for j in joints[1:]),
        idx_v=(0,) + tuple(int(j.idx_v) for j in joints[1:]),
        frame_names=tuple(str(frame.name) for frame in frames),
        frame_parents=tuple(int(frame.parentJoint) for frame in frames),
        nq=int(pin_model.nq),
        nv=int(pin_model.nv),
        joint_axes=_to_jax(axes),
        joint_placement_rotation=_to_jax([m.rotation for m in placements]),
        joint_placement_translation=_to_jax([m.translation for m in placements]),
        body_mass=_to_jax([inertia.mass for inertia in inertias]),
        body_com=_to_jax([inertia.lever for inertia in inertias]),
        body_inertia=_to_jax([inertia.inertia for inertia in inertias]),
        frame_placement_rotation=_to_jax([frame.placement.rotation for frame in frames]).reshape(-1, 3, 3),
        frame_placement_translation=_to_jax([frame.placement.translation for frame in frames]).reshape(-1, 3),
        lower_position_limit=_to_jax(_limits_to_inf(pin_model.lowerPositionLimit)),
        upper_position_limit=_to_jax(_limits_to_inf(pin_model.upperPositionLimit)),
        velocity_limit=_to_jax(_limits_to_inf(pin_model.velocityLimit)),
        effort_limit=_to_jax(_limits_to_inf(pin_model.effortLimit)),
        armature=_to_jax(pin_model.armature),
        gravity=_to_jax(gravity.linear),
    )


def _import_pinocchio() -> Any:
    try:
        import pinocchio
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            "loading URDF files needs Pinocchio: pip install 'rsmooth[sim]' (package 'pin')"
        ) from error
    return pinocchio


def load_urdf(urdf: str | pathlib.Path, *, floating_base: bool = True, check_inertia: bool = True) -> Model:
    """Loads a URDF model (kinematics and inertias only; meshes are not read).

    Args:
        urdf: path to the ``.urdf`` file, or the URDF's XML text itself (a string whose first
            non-blank character is ``<``), e.g. a model written by a script.
        floating_base: if true the root link is attached to the world by a free-flyer joint
            named ``"root_joint"`` (as ``pin.buildModelFromUrdf(path, JointModelFreeFlyer())``);
            otherwise it is fixed to the world.
        check_inertia: reject a body (a link with the links fixed to it) whose rotational
            inertia has a negative principal moment or violates the triangle inequality
            ``I1 + I2 >= I3`` (relative tolerance 1e-6), as MuJoCo does. Negative or
            non-finite masses and non-finite inertias are rejected either way.

    Returns:
        The model.

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: if the file or text is not a valid URDF, has an unsupported joint type, or
            describes impossible inertia (the message names the link and the value).

    Example:
        >>> model = load_urdf('''<robot name="pendulum">
        ...   <link name="base"/>
        ...   <link name="arm"><inertial><mass value="1"/><origin xyz="0 0 -0.5"/>
        ...     <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.01"/></inertial></link>
        ...   <joint name="hinge" type="revolute"><parent link="base"/><child link="arm"/>
        ...     <axis xyz="0 1 0"/><limit effort="1" lower="-3" upper="3" velocity="10"/></joint>
        ... </robot>''', floating_base=False)
        >>> model.nq, model.joint_names
        (1, ('universe', 'hinge'))
    """
    text = isinstance(urdf, str) and urdf.lstrip().startswith("<")
    source = "the URDF text" if text else pathlib.Path(urdf)
    if not text and not source.is_file():
        raise FileNotFoundError(f"URDF file not found: {source}")
    # Checked here first so that a malformed file gives a Python error naming the path,
    # not urdfdom's messages on stderr followed by Pinocchio's generic exception.
    try:
        root = ElementTree.fromstring(urdf) if text else ElementTree.parse(source).getroot()
    except ElementTree.ParseError as error:
        raise ValueError(f"{source} is not well-formed XML: {error}") from None
    if root.tag != "robot":
        raise ValueError(f"{source} is not a URDF file: its root element is <{root.tag}>, not <robot>")
    _check_urdf_inertials(root, source)
    pin = _import_pinocchio()
    build = (lambda *a: pin.buildModelFromXML(urdf, *a)) if text else (lambda *a: pin.buildModelFromUrdf(str(source), *a))
    try:
        pin_model = build(pin.JointModelFreeFlyer()) if floating_base else build()
    except Exception as error:  # Pinocchio raises ValueError/RuntimeError from C++
        raise ValueError(f"Pinocchio could not build a model from {source}: {error}") from None
    if check_inertia:
        _check_body_inertias(pin, pin_model, source)
    return from_pinocchio(pin_model)


_MODEL_FORMAT = "rsmooth.sim.Model/1"


def save_model(path: str | pathlib.Path, model: Model) -> pathlib.Path:
    """Writes a model to a ``.npz`` file that :func:`load_model` reads without Pinocchio.

    A model is built once where Pinocchio is installed (:func:`load_urdf`) and can then be used
    where it is not (a GPU node, a minimal container): the file holds every array field in
    float64 and the structural fields (names, types, parents, offsets) as JSON. The file is
    written to a temporary name and renamed, so an interrupted call leaves no partial file.

    Args:
        path: the file to write (``.npz`` is appended by NumPy if missing: the returned path
            is the one written).
        model: the model.

    Returns:
        The path of the written file.
    """
    import json

    from rsmooth._files import atomic_path

    if not isinstance(model, Model):
        raise TypeError(f"model must be an rsmooth.sim.Model, got {type(model).__name__}")
    path = pathlib.Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    static_names, array_names = _model_fields()
    static = {name: getattr(model, name) for name in static_names}
    arrays = {name: np.asarray(getattr(model, name), dtype=np.float64) for name in array_names}
    with atomic_path(path) as temporary, open(temporary, "wb") as file:
        np.savez(file, __format__=np.array(_MODEL_FORMAT), __static__=np.array(json.dumps(static)), **arrays)
    return path


def load_model(path: str | pathlib.Path) -> Model:
    """Reads a model written by :func:`save_model` (no Pinocchio needed).

    Args:
        path: the ``.npz`` file.

    Returns:
        The model, equal to the one saved (arrays bit for bit).

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: if the file is not a saved model, or its fields do not form a valid model.

    Example:
        >>> import tempfile, pathlib
        >>> model = free_body(2.0, [1e-2, 2e-2, 3e-2])
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     loaded = load_model(save_model(pathlib.Path(folder) / "body.npz", model))
        >>> loaded.frame_names == model.frame_names, float(loaded.body_mass[1])
        (True, 2.0)
    """
    import json
    import zipfile

    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            contents = {name: data[name] for name in data.files}
    except (ValueError, OSError, zipfile.BadZipFile) as error:
        raise ValueError(f"{path} is not a model file written by rsmooth.sim.save_model: {error}") from None
    if str(contents.get("__format__", "")) != _MODEL_FORMAT:
        raise ValueError(f"{path} is not a model file written by rsmooth.sim.save_model (no {_MODEL_FORMAT!r} marker)")
    static = json.loads(str(contents["__static__"]))
    static_names, array_names = _model_fields()
    missing = [name for name in static_names if name not in static] + [name for name in array_names if name not in contents]
    if missing:
        raise ValueError(f"{path} lacks the model fields {missing}")
    fields = {name: tuple(static[name]) if isinstance(static[name], list) else static[name] for name in static_names}
    fields.update({name: _to_jax(contents[name]) for name in array_names})
    return Model(**fields)


def _model_fields() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Model's structural (static) and array field names, read off its dataclass fields."""
    import dataclasses

    fields = dataclasses.fields(Model)
    return (
        tuple(f.name for f in fields if f.metadata.get("static", False)),
        tuple(f.name for f in fields if not f.metadata.get("static", False)),
    )


def example_robot_data_root() -> pathlib.Path:
    """The folder of the files shipped by the installed ``example-robot-data`` package
    (``robots/<name>_description/{robots,srdf,meshes}``), found without importing it.

    Raises:
        FileNotFoundError: if example-robot-data is not installed.
    """
    relative = pathlib.Path("cmeel.prefix", "share", "example-robot-data")
    candidates = []
    try:
        distribution = importlib.metadata.distribution("example-robot-data")
        candidates.append(pathlib.Path(str(distribution.locate_file(relative))))
    except importlib.metadata.PackageNotFoundError:
        pass
    candidates += [pathlib.Path(entry) / relative for entry in sys.path if entry]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        "example-robot-data is not installed (its files are looked for under "
        f"<site-packages>/{relative.as_posix()}): pip install example-robot-data"
    )


def solo12_urdf_path() -> pathlib.Path:
    """Path of the Solo-12 URDF shipped by the ``example-robot-data`` package.

    Returns:
        Path to ``robots/solo_description/robots/solo12.urdf``.

    Raises:
        FileNotFoundError: if example-robot-data is not installed.
    """
    path = example_robot_data_root() / "robots" / "solo_description" / "robots" / "solo12.urdf"
    if not path.is_file():
        raise FileNotFoundError(f"Solo-12 URDF not found at {path}")
    return path


def _solo12_srdf_path() -> pathlib.Path:
    path = example_robot_data_root() / "robots" / "solo_description" / "srdf" / "solo.srdf"
    if not path.is_file():
        raise FileNotFoundError(f"Solo SRDF not found at {path}")
    return path


def solo12_standing_configuration(model: Model | None = None, *, state: str = "standing") -> jax.Array:
    """The Solo-12 reference posture named ``state`` in the package's SRDF.

    Args:
        model: the Solo-12 model whose joint ordering to use; default: ``load_urdf(
            solo12_urdf_path())`` (free-flyer base). Joints of the SRDF state that the model
            lacks (e.g. ``root_joint`` for a fixed base) are ignored.
        state: SRDF ``group_state`` name (``"standing"`` or ``"straight_standing"``).

    Returns:
        Configuration vector of shape ``(model.nq,)``.

    Raises:
        ValueError: if the state is missing, or does not set every joint of the model.
    """
    if model is None:
        model = load_urdf(solo12_urdf_path())
    srdf = _solo12_srdf_path()
    values: dict[str, list[float]] = {}
    for group_state in ElementTree.parse(srdf).getroot().iter("group_state"):
        if group_state.get("name") == state:
            for joint in group_state.iter("joint"):
                values[joint.get("name", "")] = [float(x) for x in joint.get("value", "").split()]
            break
    else:
        raise ValueError(f"no group_state named {state!r} in {srdf}")
    q = np.zeros(model.nq)
    for i in range(1, model.njoints):
        name = model.joint_names[i]
        if name not in values:
            raise ValueError(f"state {state!r} of {srdf} does not set joint {name!r}")
        if len(values[name]) != model.joint_nq(i):
            raise ValueError(f"state {state!r} sets {len(values[name])} values for joint {name!r}")
        q[model.idx_q[i] : model.idx_q[i] + model.joint_nq(i)] = values[name]
    return _to_jax(q)


def free_body(mass: float, inertia: Any, *, name: str = "body", gravity=(0.0, 0.0, -9.81)) -> Model:
    """A single rigid body attached to the world by a free-flyer joint (no Pinocchio needed).

    The body frame is at the centre of mass. Frames: ``"universe"``, ``"root_joint"`` and
    ``name`` (the body), all Pinocchio-style.

    Args:
        mass: mass in kg, ``> 0``.
        inertia: rotational inertia about the centre of mass in body axes, ``(3, 3)``
            symmetric positive definite (or the diagonal ``(3,)``).
        name: name of the body frame.
        gravity: linear gravity in the world frame.

    Returns:
        The model: ``nq = 7``, ``nv = 6``.

    Example:
        >>> model = free_body(1.0, [1e-3, 1e-3, 1e-3])
        >>> model.nq, model.nv, model.frame_names
        (7, 6, ('universe', 'root_joint', 'body'))
    """
    if isinstance(mass, bool) or np.ndim(mass) != 0 or not (np.isfinite(mass) and mass > 0):
        raise ValueError(f"mass must be a positive, finite number, got {mass!r}")
    inertia = np.asarray(inertia, dtype=np.float64)
    if inertia.shape == (3,):
        inertia = np.diag(inertia)
    if inertia.shape != (3, 3):
        raise ValueError(f"inertia must have shape (3, 3) or (3,), got {inertia.shape}")
    if not np.all(np.isfinite(inertia)):
        raise ValueError(f"inertia must be finite, got {inertia.tolist()}")
    if not (np.allclose(inertia, inertia.T) and np.all(np.linalg.eigvalsh(inertia) > 0)):
        raise ValueError(f"inertia must be symmetric positive definite, got {inertia.tolist()}")
    eye = np.eye(3)
    return Model(
        joint_names=("universe", "root_joint"),
        joint_types=(UNIVERSE, FREE_FLYER),
        parents=(0, 0),
        idx_q=(0, 0),
        idx_v=(0, 0),
        frame_names=("universe", "root_joint", name),
        frame_parents=(0, 1, 1),
        nq=7,
        nv=6,
        joint_axes=_to_jax(np.zeros((2, 3))),
        joint_placement_rotation=_to_jax([eye, eye]),
        joint_placement_translation=_to_jax(np.zeros((2, 3))),
        body_mass=_to_jax([0.0, mass]),
        body_com=_to_jax(np.zeros((2, 3))),
        body_inertia=_to_jax([np.zeros((3, 3)), inertia]),
        frame_placement_rotation=_to_jax([eye, eye, eye]),
        frame_placement_translation=_to_jax(np.zeros((3, 3))),
        lower_position_limit=_to_jax(np.full(7, -np.inf)),
        upper_position_limit=_to_jax(np.full(7, np.inf)),
        velocity_limit=_to_jax(np.full(6, np.inf)),
        effort_limit=_to_jax(np.full(6, np.inf)),
        armature=_to_jax(np.zeros(6)),
        gravity=_to_jax(gravity),
    )
