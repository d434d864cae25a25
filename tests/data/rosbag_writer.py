"""Test helper: synthetic two-car trajectories and ROS1 bags in the format of the authors'
human–human recordings (topics ``/object_state/1`` and ``/object_state/2`` of type
``vtd_interface/rdb_object_state``), written with ``rosbags`` from message definitions given here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

MSG_TYPE = "vtd_interface/msg/rdb_object_state"
DEFINITIONS = {
    "vtd_interface/msg/rdb_coord": (
        "float64 x\nfloat64 y\nfloat64 z\nfloat32 h\nfloat32 p\nfloat32 r\nuint8 flags\nuint8 type\nuint16 system\n"
    ),
    "vtd_interface/msg/rdb_object_state_base": "uint32 id\nrdb_coord pos\n",
    "vtd_interface/msg/rdb_object_state_ext": "rdb_coord speed\nrdb_coord accel\n",
    MSG_TYPE: "float64 simTime\nrdb_object_state_base base\nrdb_object_state_ext ext\n",
}

TYPESTORE = get_typestore(Stores.ROS1_NOETIC)
for _name, _text in DEFINITIONS.items():
    TYPESTORE.register(get_types_from_msg(_text, _name))


def car_states(t: np.ndarray, x0: float, v: float, y0: float, y1: float, t_change: float, duration: float) -> np.ndarray:
    """States ``[len(t), 6]`` (x, y, xd, yd, xdd, ydd in m, m/s, m/s²) at times ``t`` (s) of a car
    driving at constant speed ``v`` from ``x0`` and moving laterally from ``y0`` to ``y1`` during
    ``[t_change, t_change + duration]`` with a raised-cosine lateral speed (so ``ydd`` is continuous)."""
    s = np.clip((t - t_change) / duration, 0.0, 1.0)
    dy = y1 - y0
    phase = 2 * np.pi * s
    return np.stack(
        [
            x0 + v * t,
            y0 + dy * (s - np.sin(phase) / (2 * np.pi)),
            np.full_like(t, v),
            dy / duration * (1 - np.cos(phase)),
            np.zeros_like(t),
            dy / duration**2 * 2 * np.pi * np.sin(phase),
        ],
        axis=1,
    )


def sim_times(start: float, stop: float, rate: float = 60.0, jitter: float = 0.0, seed: int = 0) -> np.ndarray:
    """Simulator stamps from ``start`` to ``stop`` (s) at ``rate`` Hz, each moved by up to
    ``±jitter`` s (uniform), ``[n]`` increasing."""
    t = np.arange(start, stop, 1.0 / rate)
    return t + np.random.default_rng(seed).uniform(-jitter, jitter, len(t))


def write_bag(path: Path, tracks: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Write a ROS1 bag at ``path`` with one ``rdb_object_state`` topic per entry of ``tracks``:
    ``topic -> (simTime [n] s, states [n, 6])``. Bag timestamps follow ``simTime``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    types = TYPESTORE.types
    coord = types["vtd_interface/msg/rdb_coord"]
    base, ext, state = (types[f"{MSG_TYPE}{suffix}"] for suffix in ("_base", "_ext", ""))

    def xy(x: float, y: float):
        return coord(x=float(x), y=float(y), z=0.0, h=0.0, p=0.0, r=0.0, flags=0, type=0, system=0)

    messages = []  # (simTime, connection index, message)
    for k, (times, states) in enumerate(tracks.values()):
        for t, (x, y, xd, yd, xdd, ydd) in zip(times, states):
            msg = state(simTime=float(t), base=base(id=k + 1, pos=xy(x, y)), ext=ext(speed=xy(xd, yd), accel=xy(xdd, ydd)))
            messages.append((float(t), k, msg))
    messages.sort(key=lambda m: m[:2])
    with Writer(path) as writer:
        connections = [writer.add_connection(topic, MSG_TYPE, typestore=TYPESTORE) for topic in tracks]
        for t, k, msg in messages:
            writer.write(connections[k], int(t * 1e9), TYPESTORE.serialize_ros1(msg, MSG_TYPE))
