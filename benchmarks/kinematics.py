"""Speed of the twin's kinematics: batched DH FK, closed-form IK, perturbed-table IK,
MuJoCo FK and collision queries, scene build. Prints figures; asserts nothing.

Run: python benchmarks/kinematics.py
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import time  # noqa: E402

import numpy as np  # noqa: E402

from calib.dh import NOMINAL_TABLES, DHDeltas, forward_kinematics  # noqa: E402
from twin.ik import solve_ik  # noqa: E402
from twin.phantoms import PhantomConfig, build_phantom, build_tank  # noqa: E402
from twin.scene import Scene, SceneModel  # noqa: E402
from twin.tools import ToolsConfig  # noqa: E402


def rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    fn()
    return n / (time.perf_counter() - t0)


def main() -> None:
    rng = np.random.default_rng(0)
    nominal = NOMINAL_TABLES["ur3"]
    rms = (np.radians(2.51), 0.24e-3, 1.51e-3, np.radians(0.27))
    perturbed = nominal.with_deltas(
        DHDeltas.from_array(np.column_stack([rng.normal(0, s, 6) for s in rms]))
    )
    q = rng.uniform(-np.pi, np.pi, (100_000, 6))
    print(f"dh_fk_batched_per_s={rate(lambda: forward_kinematics(nominal, q), len(q)):.0f}")

    qs = q[:500]
    Ts = forward_kinematics(nominal, qs)
    ik_rate = rate(
        lambda: [solve_ik(nominal, T, qi) for T, qi in zip(Ts, qs, strict=True)], len(qs)
    )
    print(f"ik_nominal_per_s={ik_rate:.0f}")

    keep = (np.abs(q[:, 2]) < 2.6) & (np.abs(np.sin(q[:, 4])) > 0.2)
    qp = q[keep][:100]
    Tp = forward_kinematics(perturbed, qp)
    ik_rate = rate(
        lambda: [solve_ik(perturbed, T, qi) for T, qi in zip(Tp, qp, strict=True)], len(qp)
    )
    print(f"ik_perturbed_per_s={ik_rate:.0f}")

    pc = PhantomConfig()
    scene = Scene(
        perturbed,
        ToolsConfig(),
        build_phantom(pc),
        pc.T_base_phantom,
        build_tank(pc),
        pc.T_base_tank,
    )
    t0 = time.perf_counter()
    sm = SceneModel(scene)
    print(f"scene_build_s={time.perf_counter() - t0:.3f}")
    qm = q[:2000]
    print(f"mujoco_fk_per_s={rate(lambda: [sm.flange_pose(qi) for qi in qm], len(qm)):.0f}")
    print(f"collision_queries_per_s={rate(lambda: [sm.collisions(qi) for qi in qm], len(qm)):.0f}")


if __name__ == "__main__":
    main()
