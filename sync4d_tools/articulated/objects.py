"""The articulated-object suite: Meta-World models (MIT) and procedural MJCF objects, as MuJoCo scenes.

Each :class:`SuiteObject` names an MJCF body (a Meta-World asset included from the installed ``metaworld``
wheel, or a procedural body written here), the joints that move and their trajectories. Rendering lives in
:mod:`sync4d_tools.articulated.render`.

Meta-World assets: ``metaworld==3.1.1`` (MIT), ``metaworld/assets/objects``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SuiteObject:
    """One articulated object of the suite.

    Attributes:
        name: short name (folder name of its clips).
        body_xml: the MJCF ``<body>`` of the object (Meta-World: an ``<include>`` of its asset file).
        dependencies: MJCF ``<include>`` of its assets (materials, meshes) or procedural ``<asset>`` text.
        joints: names of the moving joints (MuJoCo joint names), one per moving part.
        start: (J,) joint value at frame 0 [rad or m].
        turn: (J,) joint value at the motion's far end [rad or m]; the motion goes start -> turn -> start.
        textured: whether the surfaces carry texture (procedural objects) - for the suite's table only.
        source: provenance for attribution.
    """

    name: str
    body_xml: str
    dependencies: str
    joints: tuple[str, ...]
    start: tuple[float, ...]
    turn: tuple[float, ...]
    textured: bool
    source: str

    def trajectory(self, num_frames: int) -> np.ndarray:
        """(T, J) joint values: start -> turn -> start on a raised cosine [rad or m]."""
        phase = (1.0 - np.cos(2.0 * np.pi * np.arange(num_frames) / max(num_frames - 1, 1))) / 2.0
        start, turn = np.asarray(self.start), np.asarray(self.turn)
        return start[None] + (turn - start)[None] * phase[:, None]


def _mw(name: str, asset: str, joints: tuple[str, ...], start: tuple[float, ...], turn: tuple[float, ...]) -> SuiteObject:
    return SuiteObject(name=name, body_xml=f'<body name="object"><include file="assets/{asset}.xml"/></body>',
                       dependencies=f'<include file="assets/{asset}_dependencies.xml"/>', joints=joints, start=start,
                       turn=turn, textured=False, source=f"Meta-World {asset}.xml (metaworld==3.1.1, MIT)")


CHECKER = ('<texture name="{n}" type="cube" builtin="checker" rgb1="{a}" rgb2="{b}" width="64" height="64"/>'
           '<material name="{n}" texture="{n}" texrepeat="6 6" texuniform="true"/>')
PLAIN = '<material name="{n}" rgba="{a} 1"/>'


def _materials(textured: bool, names_colours: list[tuple[str, str, str]]) -> str:
    parts = []
    for n, a, b in names_colours:
        parts.append(CHECKER.format(n=n, a=a, b=b) if textured else PLAIN.format(n=n, a=a))
    return "<asset>" + "".join(parts) + "</asset>"


def _appliance() -> SuiteObject:
    """A kitchen appliance: a cabinet whose door swings about a vertical hinge to 100 deg and back."""
    body = ('<body name="object"><geom type="box" size="0.2 0.16 0.22" pos="0 0 0.22" material="case"/>'
            '<body name="door" pos="-0.2 -0.17 0.22"><joint name="door_hinge" type="hinge" axis="0 0 -1"/>'
            '<geom type="box" size="0.2 0.012 0.21" pos="0.2 0 0" material="door"/>'
            '<geom type="box" size="0.012 0.02 0.08" pos="0.36 -0.03 0" material="case"/></body></body>')
    deps = _materials(True, [("case", ".75 .75 .7", ".55 .55 .5"), ("door", ".3 .45 .7", ".15 .25 .45")])
    return SuiteObject("appliance_door", body, deps, ("door_hinge",), (0.0,), (np.radians(100.0),), True,
                       "procedural (sync4d)")


def _chest() -> SuiteObject:
    """A plain box whose lid starts open and closes about a horizontal hinge, then opens again."""
    body = ('<body name="object"><geom type="box" size="0.18 0.12 0.08" pos="0 0 0.08" material="box"/>'
            '<body name="lid" pos="0 0.12 0.16"><joint name="lid_hinge" type="hinge" axis="1 0 0"/>'
            '<geom type="box" size="0.18 0.12 0.01" pos="0 -0.12 0.01" material="lid"/></body></body>')
    deps = _materials(False, [("box", ".6 .35 .2", ""), ("lid", ".8 .6 .3", "")])
    return SuiteObject("chest_lid", body, deps, ("lid_hinge",), (np.radians(-80.0),), (np.radians(-10.0),), False,
                       "procedural (sync4d)")


def _desk() -> SuiteObject:
    """Three parts: a desk box with a hinged top lid and a drawer that slides out."""
    body = ('<body name="object"><geom type="box" size="0.2 0.15 0.12" pos="0 0 0.12" material="desk"/>'
            '<body name="lid" pos="0 0.15 0.24"><joint name="lid_hinge" type="hinge" axis="1 0 0"/>'
            '<geom type="box" size="0.2 0.15 0.01" pos="0 -0.15 0.01" material="lid"/></body>'
            '<body name="drawer" pos="0 -0.16 0.1"><joint name="drawer_slide" type="slide" axis="0 -1 0"/>'
            '<geom type="box" size="0.16 0.012 0.06" material="drawer"/>'
            '<geom type="box" size="0.15 0.12 0.055" pos="0 0.12 0" material="drawer"/>'
            '<geom type="box" size="0.05 0.015 0.012" pos="0 -0.025 0" material="lid"/></body></body>')
    deps = _materials(True, [("desk", ".7 .55 .4", ".5 .38 .25"), ("lid", ".35 .5 .35", ".2 .3 .2"),
                             ("drawer", ".8 .8 .85", ".55 .55 .65")])
    return SuiteObject("desk_lid_drawer", body, deps, ("lid_hinge", "drawer_slide"), (0.0, 0.0),
                       (np.radians(-70.0), 0.16), True, "procedural (sync4d)")


def suite_objects() -> list[SuiteObject]:
    """The suite's eight objects: five Meta-World models and three procedural ones (one with three parts)."""
    return [
        # Meta-World laptop: 0 = open, 1.57 = closed (shared data README); start closed, open to ~100 deg
        _mw("mw_laptop", "laptop", ("",), (1.57,), (-0.2,)),
        _mw("mw_drawer", "drawer", ("goal_slidey",), (0.0,), (-0.15,)),
        _mw("mw_window", "window", ("window_slide",), (0.0,), (0.18,)),
        _mw("mw_faucet", "faucet", ("knob_Joint_1",), (-1.2,), (1.2,)),
        _mw("mw_lever", "lever", ("LeverAxis",), (0.0,), (1.4,)),
        _appliance(),
        _chest(),
        _desk(),
    ]
