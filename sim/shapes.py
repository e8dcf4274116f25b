"""Generated test objects for registration checks: the thin, flat and symmetric shapes the
YCB meshes in ``assets/ycb`` do not cover.

A thin tool lying on the table is where segmentation and registration are weakest (its top is a
few millimetres above the table, about the depth noise; its view is nearly a plane), and a
symmetric shape has no unique pose (ADD-S scores it). The meshes are made here by code, so a
check on them is reproducible without shipping files: ``dtx sim shapes DIR`` writes them,
``dtx perception register-check DIR/*.obj`` checks them.

Every mesh is closed and manifold (the simulator requires it), in metres, with its origin at
the centre of its footprint and its lowest point at z = 0 (the simulator turns an object about
its origin and rests its lowest point on the table).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d


def _extrude(
    outline_xy_m: np.ndarray, fan_centre_xy_m: tuple[float, float], thickness_m: float
) -> o3d.geometry.TriangleMesh:
    """A flat part: the counter-clockwise outline extruded from z = 0 to ``thickness_m``.

    Caps are triangle fans from ``fan_centre_xy_m``, so the outline must be star-shaped about it
    (every outline vertex visible from it) and no vertex may be collinear with it and its neighbour.
    """
    outline = np.asarray(outline_xy_m, dtype=np.float64)
    count = len(outline)
    bottom = np.column_stack([outline, np.zeros(count)])
    top = np.column_stack([outline, np.full(count, thickness_m)])
    centres = [[*fan_centre_xy_m, 0.0], [*fan_centre_xy_m, thickness_m]]
    vertices = np.vstack([bottom, top, centres])  # bottom 0..n-1, top n..2n-1, centres 2n, 2n+1
    triangles = []
    for i in range(count):
        j = (i + 1) % count
        triangles += [
            [2 * count, j, i],
            [2 * count + 1, count + i, count + j],  # caps: normals down, up
            [i, j, count + j],
            [i, count + j, count + i],
        ]  # side: outward
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    return mesh.subdivide_midpoint(2)  # smaller triangles on the long sides: even surface sampling


def _centred(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """Footprint centre at the origin, lowest point at z = 0."""
    low, high = mesh.get_min_bound(), mesh.get_max_bound()
    mesh.translate((-(low[0] + high[0]) / 2, -(low[1] + high[1]) / 2, -low[2]))
    return mesh


def shape_meshes() -> dict[str, o3d.geometry.TriangleMesh]:
    """The generated objects by name (the file stem :func:`write_shapes` gives them)."""
    # A flat tool (a scraper or spatula): 180 mm handle 20 mm wide, a 40 x 50 mm blade, 5 mm thick.
    tool = [
        (0.0, -0.010),
        (0.130, -0.010),
        (0.130, -0.025),
        (0.180, -0.025),
        (0.180, 0.025),
        (0.130, 0.025),
        (0.130, 0.010),
        (0.0, 0.010),
    ]
    # An angle bracket lying flat: legs 100 and 60 mm long, 25 mm wide, 4 mm thick.
    bracket = [(0.0, 0.0), (0.100, 0.0), (0.100, 0.025), (0.025, 0.025), (0.025, 0.060), (0.0, 0.060)]
    return {
        "flat_tool": _centred(_extrude(np.array(tool), (0.140, 0.0), 0.005)),
        "thin_plate": _centred(_extrude(np.array([(0, 0), (0.16, 0), (0.16, 0.04), (0, 0.04)]), (0.08, 0.02), 0.004)),
        "l_bracket": _centred(_extrude(np.array(bracket), (0.0125, 0.0125), 0.004)),
        "puck": _centred(o3d.geometry.TriangleMesh.create_cylinder(0.038, 0.025, resolution=128, split=2)),
        "disc": _centred(o3d.geometry.TriangleMesh.create_cylinder(0.045, 0.008, resolution=128, split=1)),
        "cylinder": _centred(o3d.geometry.TriangleMesh.create_cylinder(0.03, 0.10, resolution=128, split=8)),
        "sphere": _centred(o3d.geometry.TriangleMesh.create_sphere(0.035, resolution=60)),
    }


def write_shapes(directory: str | Path, names: list[str] | None = None) -> list[Path]:
    """Write the generated objects (all, or ``names``) as ``DIR/<name>.obj``; their paths, in order.

    ValueError names the shapes there are when asked for an unknown one.
    """
    shapes = shape_meshes()
    names = list(shapes) if names is None else list(names)
    unknown = sorted(set(names) - set(shapes))
    if unknown:
        raise ValueError(f"no generated shape named {', '.join(unknown)}; there are {', '.join(shapes)}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in names:
        path = directory / f"{name}.obj"
        if not o3d.io.write_triangle_mesh(path, shapes[name], write_vertex_normals=False):
            raise OSError(f"could not write {path}")
        paths.append(path)
    return paths
