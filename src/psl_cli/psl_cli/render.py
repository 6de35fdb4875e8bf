"""``psl render``: one rollout of a task drawn offscreen into an animated GIF.

The rollout runs in batch mode in this process (`psl_optimizer.batch_rollout.BatchRollouts`:
the same law and physics as the graph), then its simulated joint angles, every joint's (the
passive ones too: `RolloutResult.qpos`), are replayed kinematically in the task's model
(`psl_task.arm_model.ArmModel`: joint angles, the task instance's mocap bodies,
``mj_forward``) at ``--fps`` frames per second of simulated time
(the control steps subsampled; first and last state included) and drawn with
``mujoco.Renderer``. The commanded end-effector path (the policy's reference through the
reward's end-effector sensor, `psl_task.reward_geometry.RewardGeometry.replay`) is drawn as a
thin line. If MuJoCo cannot render here (no OpenGL context), each frame is a matplotlib 3-D
stick figure of the same replay instead (the geoms of `psl_sim.scene.Scene`: capsules and
cylinders as segments, spheres as dots, boxes and planes as outlines, joints as dots);
the output line says which renderer drew the file.

Offscreen rendering needs an OpenGL context without a display: ``MUJOCO_GL=egl`` (Mesa's
software EGL works headless; osmesa and glfw do not here, DESIGN.md section 6). MuJoCo picks
its backend once, when ``mujoco`` is first imported (``import mujoco`` loads its GL context
module), so `run` sets the default first, before it imports anything that imports mujoco
(this module imports none at its top); a ``MUJOCO_GL`` set by the user wins. Not at import
time: a parser that imports this module for its options would set it for every command, and
``psl up`` would hand MUJOCO_GL=egl to all its nodes, whose ``import mujoco`` breaks on a
machine without a working EGL (as it does here under MUJOCO_GL=osmesa). In a process that
imported mujoco before without it, the renderer fails and the stick figure is drawn.

GIF only (Pillow); no video encoder is installed (imageio/ffmpeg), so ``.mp4`` is refused with
a hint (``ffmpeg -i rollout.gif rollout.mp4`` converts where ffmpeg exists). GIF stores frame
durations in hundredths of a second, and Pillow merges identical consecutive frames (a robot
at rest) into one longer frame.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from psl_optimizer.reward import RewardResult
    from psl_task.arm_model import ArmModel
    from psl_sim.scene import SceneGeom
    from psl_task.task import TaskDefinition

DEFAULT_SIZE = (480, 360)       # px, width and height
DEFAULT_FPS = 30.0              # frames per second of simulated time
MAX_SIZE = 4096                 # px, per side
OFFSCREEN_GL = 'egl'            # MUJOCO_GL unless the user set one (module docstring)
RENDERERS = ('auto', 'mujoco', 'matplotlib')    # auto: MuJoCo, else the stick figure
SUFFIXES = ('.gif',)
CAMERA_AZIMUTH = 90.0           # deg: looking along +y, at the x-z plane the planar arms use
CAMERA_ELEVATION = -15.0        # deg
CAMERA_MARGIN = 1.15            # the framed sphere is this much larger than the scene
PATH_WIDTH = 2.0                # px, the commanded path's line (MuJoCo)
PATH_RGBA = np.array([1.0, 1.0, 1.0, 0.8], dtype=np.float32)
PATH_POINTS = 150               # the commanded path is drawn through at most this many points


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``psl render``."""
    from psl_cli import options

    options.add_task(parser)
    options.add_tau(parser)
    options.add_theta_file(parser)
    parser.add_argument('-o', '--output', required=True, help='animated GIF to write (.gif)')
    parser.add_argument('--fps', type=float, default=DEFAULT_FPS,
                        help='frames per second of simulated time')
    parser.add_argument('--size', type=int, nargs=2, default=list(DEFAULT_SIZE),
                        metavar=('WIDTH', 'HEIGHT'), help='frame size in pixels')
    parser.add_argument('--renderer', choices=RENDERERS, default=RENDERERS[0],
                        help='auto: MuJoCo offscreen, the matplotlib stick figure if that '
                        'fails')


@dataclasses.dataclass(frozen=True)
class Replay:
    """A rollout replayed kinematically: the model's data at every frame."""

    arm: ArmModel                   # its data: the state of the current frame
    steps: np.ndarray               # (F,) control step of each frame
    q: np.ndarray                   # (N+1, n) measured joint angles
    commanded_path: np.ndarray      # (P, 3) end effector along the reference
    tau: np.ndarray
    evaluation: RewardResult
    world: dict = dataclasses.field(default_factory=dict)  # {body: (N+1, 7)} observed poses
    qpos: np.ndarray | None = None  # (N+1, nq) every joint as simulated, passive ones too

    def frames(self) -> Iterator[int]:
        """Puts the arm's data at each frame's state (mj_forward): every joint as the rollout
        simulated it (passive ones too: a humanoid's body that falls under a driven arm, a
        thrown ball in flight), else the driven joints and the bodies the task observes where
        they were measured; yields the step."""
        import mujoco

        data = self.arm.data
        for step in self.steps:
            if self.qpos is not None:
                data.qpos[:] = self.qpos[step]
            else:
                data.qpos[self.arm.qpos_adr] = self.q[step]
                for body, poses in self.world.items():
                    self.arm.set_body_pose(body, poses[step])
            mujoco.mj_forward(self.arm.model, data)
            yield step


def frame_steps(num_steps: int, control_rate: float, fps: float) -> np.ndarray:
    """The control steps (states 0..num_steps) shown at `fps` frames per second of simulated
    time, the first and the last state included."""
    duration = num_steps / control_rate
    times = np.arange(0.0, duration, 1.0 / fps)
    steps = np.round(times * control_rate).astype(int)
    return np.unique(np.append(np.minimum(steps, num_steps), num_steps))


def replay_rollout(task: TaskDefinition, tau: np.ndarray, theta: np.ndarray, fps: float) -> Replay:
    """Roll theta out on tau in batch mode and set up its kinematic replay.

    Raises:
        ValueError: a theta of the wrong size or not finite (TaskError, a ValueError, for tau).
    """
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_task.arm_model import ArmModel

    rollouts = BatchRollouts(task, n_threads=1)
    result = rollouts.run(theta[None], tau)[0]
    last = len(result.q_ref) - 1
    shown = np.unique(np.append(np.arange(0, last, max(1, last // PATH_POINTS)), last))
    commanded = rollouts.geometry.replay(result.q_ref[None, shown], tau[None]).end_effector[0]
    arm = ArmModel(task)
    arm.reset(tau)                          # the task instance's bodies placed
    return Replay(arm=arm, steps=frame_steps(task.num_steps_of(tau), task.control_rate, fps),
                  q=result.q, commanded_path=commanded, tau=tau,
                  evaluation=result.evaluation, world=result.world or {}, qpos=result.qpos)


def scene_bounds(replay: Replay) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius [m] of what moves or is placed (arm and obstacle geoms over
    all frames, the commanded path): what the camera frames."""
    from psl_sim.scene import ARM, OBSTACLES, Scene

    scene = Scene(replay.arm.model)
    drawn = [k for k, g in enumerate(scene.geoms) if g.namespace in (ARM, OBSTACLES)]
    reach = np.array([np.max(scene.geoms[k].size[:2]) for k in drawn])    # (G,) m
    points = [replay.commanded_path]
    for _ in replay.frames():
        position, rotation = scene.geom_poses(replay.arm.data)
        for k, r in zip(drawn, reach):       # the ends of each geom's long axis
            points.append(position[k] + np.outer([-r, r], rotation[k][:, 2]))
    points = np.vstack(points)
    low, high = points.min(axis=0), points.max(axis=0)
    return (low + high) / 2, max(float(np.linalg.norm(high - low)) / 2, 0.1)


# -- MuJoCo -----------------------------------------------------------------------------------
def render_mujoco(replay: Replay, width: int, height: int) -> list[np.ndarray]:
    """Frames (H, W, 3) uint8 from MuJoCo's offscreen renderer. Raises whatever the OpenGL
    stack raises when it cannot render."""
    import mujoco

    model = replay.arm.model
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    centre, radius = scene_bounds(replay)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = centre
    camera.azimuth, camera.elevation = CAMERA_AZIMUTH, CAMERA_ELEVATION
    half_vertical = np.radians(model.vis.global_.fovy) / 2
    half_horizontal = np.arctan(np.tan(half_vertical) * width / height)
    camera.distance = CAMERA_MARGIN * radius / np.sin(min(half_vertical, half_horizontal))
    frames = []
    with warnings.catch_warnings():      # glfw warns (no display) before it fails
        warnings.simplefilter('ignore')
        renderer = mujoco.Renderer(model, height=height, width=width)
    try:
        for _ in replay.frames():
            renderer.update_scene(replay.arm.data, camera=camera)
            _add_path(renderer.scene, replay.commanded_path)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
    return frames


def _add_path(scene, path: np.ndarray) -> None:
    """The commanded path as lines between its points, appended to a MjvScene."""
    import mujoco

    for start, end in zip(path[:-1], path[1:]):
        if scene.ngeom >= scene.maxgeom:
            return
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_LINE, np.zeros(3), np.zeros(3),
                            np.eye(3).ravel(), PATH_RGBA)
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_LINE, PATH_WIDTH, start, end)
        scene.ngeom += 1


# -- matplotlib -------------------------------------------------------------------------------
def render_stick_figure(replay: Replay, width: int, height: int) -> list[np.ndarray]:
    """Frames (H, W, 3) uint8: a matplotlib 3-D stick figure of each frame's geoms and joints
    (Agg canvas: no display, no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from psl_sim.scene import Scene, ShapeKind

    model, data = replay.arm.model, replay.arm.data
    scene = Scene(model)
    # boxes and planes: the extent and top face of the box that draws them (a plane's may be
    # infinite in the model), from their CUBE shape
    boxes = {s.geom: (s.scale / 2, s.scale[2] / 2 + s.axial_offset) for s in scene.shapes
             if s.kind == ShapeKind.CUBE}
    centre, radius = scene_bounds(replay)
    dpi = 100
    figure = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(figure)
    axes = figure.add_axes((0, 0, 1, 1), projection='3d')
    frames = []
    for _ in replay.frames():
        axes.clear()
        axes.set_axis_off()
        axes.view_init(elev=-CAMERA_ELEVATION, azim=CAMERA_AZIMUTH - 180.0)
        for c, (low, high) in enumerate(zip(centre - radius, centre + radius)):
            (axes.set_xlim, axes.set_ylim, axes.set_zlim)[c](low, high)
        axes.set_box_aspect((1, 1, 1))
        position, rotation = scene.geom_poses(data)
        for geom, p, r in zip(scene.geoms, position, rotation):
            _draw_geom(axes, geom, p, r, boxes.get(geom.geom))
        axes.scatter(*data.xanchor[replay.arm.joint_ids].T, color='black', s=12,
                     depthshade=False)
        axes.plot(*replay.commanded_path.T, color='0.4', linewidth=0.8, linestyle='--')
        canvas.draw()
        frames.append(np.asarray(canvas.buffer_rgba())[:, :, :3].copy())
    return frames


def _draw_geom(axes, geom: SceneGeom, position: np.ndarray, rotation: np.ndarray,
               box: tuple[np.ndarray, float] | None) -> None:
    """One geom of the stick figure: a capsule or cylinder as a segment along its axis, a
    sphere or ellipsoid as a dot, a box or plane as the outline of its top face (`box`: half
    extents (3,) and height of the top face above the centre), a mesh as a square dot."""
    import mujoco

    colour = np.clip(geom.rgba, 0.0, 1.0)
    kind = geom.type
    if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        ends = position + np.outer([-geom.size[1], geom.size[1]], rotation[:, 2])
        axes.plot(*ends.T, color=colour, linewidth=max(1.0, 200 * geom.size[0]),
                  solid_capstyle='round')
    elif kind in (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_ELLIPSOID):
        axes.scatter(*position, color=colour, s=max(4.0, (400 * geom.size[0]) ** 2),
                     depthshade=False)
    elif box is not None:
        half, top = box
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * half[:2]
        outline = position + corners @ rotation[:, :2].T + top * rotation[:, 2]
        axes.plot(*outline.T, color=colour, linewidth=1.0)
    elif kind == mujoco.mjtGeom.mjGEOM_MESH:
        axes.scatter(*position, color=colour, s=9, marker='s', depthshade=False)


RENDER = {'mujoco': (render_mujoco, 'MuJoCo offscreen renderer'),
          'matplotlib': (render_stick_figure, 'matplotlib stick figure')}


# -- the command ------------------------------------------------------------------------------
def write_gif(frames: list[np.ndarray], path: Path, fps: float) -> None:
    """An animated GIF that loops, one frame per 1/fps s (in GIF's hundredths)."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:],
                   duration=int(round(1000.0 / fps)), loop=0)


def _check_output(output: str, width: int, height: int, fps: float, control_rate: float) -> Path:
    path = Path(output)
    if path.suffix.lower() not in SUFFIXES:
        hint = (' (no video encoder is installed: write a .gif, then e.g. '
                f'ffmpeg -i {path.with_suffix(".gif").name} {path.name})'
                if path.suffix.lower() in ('.mp4', '.webm', '.mkv', '.avi', '.mov') else '')
        raise ValueError(f'cannot write {path.name!r}: the output must be a {", ".join(SUFFIXES)}'
                         f' file{hint}')
    if not path.parent.is_dir():
        raise ValueError(f'the folder {path.parent} does not exist')
    if not (0 < width <= MAX_SIZE and 0 < height <= MAX_SIZE):
        raise ValueError(f'--size must be 1..{MAX_SIZE} pixels per side, got {width} {height}')
    if not 0 < fps <= control_rate:
        raise ValueError(f'--fps must be in (0, {control_rate:g}] (the control rate), got {fps:g}')
    return path


def select_offscreen_gl() -> str:
    """Set MUJOCO_GL to `OFFSCREEN_GL` unless the user set it or mujoco is imported already
    (then it is too late: module docstring); returns what MuJoCo uses, as text."""
    if 'MUJOCO_GL' not in os.environ and 'mujoco' in sys.modules:
        return 'MUJOCO_GL unset when mujoco was imported'
    return 'MUJOCO_GL=' + os.environ.setdefault('MUJOCO_GL', OFFSCREEN_GL)


def run(args: argparse.Namespace) -> int:
    """``psl render``: 0 when written, 2 for bad input, 1 when no renderer could draw."""
    gl = select_offscreen_gl()                  # before anything imports mujoco
    from psl_cli.options import fail
    from psl_cli.vectors import load_vector
    from psl_controller.policy import policy_for
    from psl_task.task import TaskError, load_task

    width, height = args.size
    try:
        task = load_task(args.task)
        output = _check_output(args.output, width, height, args.fps, task.control_rate)
        tau = task.tau_default if args.tau is None else task.validate_tau(args.tau)
        theta = (policy_for(task).default_theta if args.theta_file is None
                 else load_vector(args.theta_file))
        replay = replay_rollout(task, tau, theta, args.fps)
    except (TaskError, OSError, ValueError) as exc:
        return fail('psl render', exc, 2)
    names = ['mujoco', 'matplotlib'] if args.renderer == 'auto' else [args.renderer]
    failed = ''
    for name in names:
        render, label = RENDER[name]
        if name == 'mujoco':
            label += f' ({gl})'
        try:
            frames = render(replay, width, height)
        except Exception as exc:  # noqa: BLE001 - whatever the OpenGL stack raises
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            failed = f'{label} failed: {reason}'
            continue
        write_gif(frames, output, args.fps)
        ev = replay.evaluation
        note = f' ({failed})' if failed else ''
        print(f'wrote {output}: {len(frames)} frames {width}x{height} at {args.fps:g} fps, '
              f'{label}{note}; tau {replay.tau.tolist()}, reward {ev.reward:.4f}, '
              f'fulfilled {ev.fulfilled}')
        return 0
    return fail('psl render', failed, 1)
