#!/usr/bin/env python3
"""Reference torques of the PUMA 560 from Corke's Robotics Toolbox for Python
(roboticstoolbox.models.DH.Puma560: standard DH, Armstrong/Khatib/Burdick 1986
link parameters, motor inertia, gear ratios, viscous and asymmetric Coulomb
friction), for tests/modules/test_robotics.cpp (issue #20, item 4).

The toolbox is not a Debian package: run this in a virtual environment, once,
when the reference is to be regenerated (the output is committed):

    python3 -m venv /tmp/rtb && /tmp/rtb/bin/pip install roboticstoolbox-python==1.5.0
    /tmp/rtb/bin/python tools/puma560_reference.py > tests/modules/data/puma560_rtb.json

For each standard pose (qz, qr, qn, qs) with the velocities and accelerations
below: gravload(q); rne(q, qd, qdd) of the full model; and rne of the model
with its Coulomb friction removed (nofriction(coulomb=True, viscous=False)),
which keeps the motor inertia and the viscous friction. Also each link's
parameters as the toolbox holds them (DH, mass, centre of mass, inertia, and
at the motor Jm, G, B and Tc = [forward, backward]), so the test can check the
C++ model's constants against the toolbox's, not only the torques they give.
"""
import json
import sys

import numpy as np
import roboticstoolbox as rtb

QD = [0.5, -0.4, 0.3, 1.0, -0.8, 0.6]      # rad/s
QDD = [1.0, 0.5, -0.7, 2.0, 1.5, -1.0]     # rad/s^2


def main():
    robot = rtb.models.DH.Puma560()
    no_coulomb = robot.nofriction(coulomb=True, viscous=False)
    cases = []
    for name in ("qz", "qr", "qn", "qs"):
        q = np.asarray(getattr(robot, name), dtype=float)
        cases.append({
            "pose": name,
            "q": q.tolist(),
            "qd": QD,
            "qdd": QDD,
            "gravload": np.asarray(robot.gravload(q)).tolist(),
            "rne": np.asarray(robot.rne(q, QD, QDD)).tolist(),
            "rne_no_coulomb": np.asarray(no_coulomb.rne(q, QD, QDD)).tolist(),
        })
    links = []
    for link in robot.links:
        links.append({
            "a": float(link.a), "alpha": float(link.alpha), "d": float(link.d),
            "offset": float(link.offset), "m": float(link.m),
            "r": np.asarray(link.r, dtype=float).ravel().tolist(),
            "I": np.asarray(link.I, dtype=float).tolist(),
            "Jm": float(link.Jm), "G": float(link.G), "B": float(link.B),
            "Tc": np.asarray(link.Tc, dtype=float).ravel().tolist(),
        })
    out = {
        "source": "roboticstoolbox.models.DH.Puma560",
        "roboticstoolbox": rtb.__version__,
        "numpy": np.__version__,
        "python": sys.version.split()[0],
        "gravity": np.asarray(robot.gravity).tolist(),
        "base_height_d1": robot.links[0].d,
        "links": links,
        "cases": cases,
    }
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
