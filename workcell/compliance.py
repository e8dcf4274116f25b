"""How far a GelSight's gel gives under a grasp: the elastomer as a Winkler (mattress) layer.

Every point of the gel pushes back with a pressure proportional to its own compression, p = k
delta, k = E / t (the gel's Young's modulus over the elastomer's thickness:
``workcell.parts.GripperSpec.foundation_stiffness_n_per_mm3``; 0.25 MPa / 2 mm = 0.125 N/mm of
indentation per mm² of contact). The simulated world presses its gels by it (sim.grasp_contact),
and the pipeline places a grasped object between the gels by it (perception.gripper_centring):
both gels carry the grasp force, each pressed as deep as its own contact needs.
"""

from __future__ import annotations

import numpy as np

# Spacing (mm) of the grid over a gel's face on which the first touch and the force balance are
# found, by the simulated world and by the pipeline alike.
CONTACT_GRID_MM = 0.3


def contact_grid_shape(gel_size_m: tuple[float, float]) -> tuple[tuple[int, int], float]:
    """((rows along gel z, cols along gel x), cell area mm²) of the CONTACT_GRID_MM grid over a
    gel face of ``gel_size_m`` (extent along gel x, gel z)."""
    x_mm, z_mm = gel_size_m[0] * 1e3, gel_size_m[1] * 1e3
    cols, rows = max(2, round(x_mm / CONTACT_GRID_MM)), max(2, round(z_mm / CONTACT_GRID_MM))
    return (rows, cols), (x_mm / cols) * (z_mm / rows)


def indentation_for_force_mm(
    gaps_mm: np.ndarray, cell_area_mm2: float, force_n: float, stiffness_n_per_mm3: float, thickness_mm: float
) -> tuple[float, float, bool]:
    """Rigid approach d (mm) of an object into the gel past the gel plane so that ``force_n`` =
    k * cell_area * sum(max(0, d - gap_i)) over the cells' ``gaps_mm`` (the object's distance
    from the gel plane per cell of ``cell_area_mm2``, +inf where nothing is in front; the
    first touch at the least gap), k = ``stiffness_n_per_mm3``. Returns (d, contact area mm²,
    saturated): d is capped at ``thickness_mm``, where the elastomer is fully compressed and the
    rigid backing carries the rest. No gap or no force: (0, 0, False)."""
    gaps = np.sort(gaps_mm[np.isfinite(gaps_mm)])
    if gaps.size == 0 or force_n <= 0:
        return 0.0, 0.0, False
    target = force_n / (stiffness_n_per_mm3 * cell_area_mm2)  # the sum of the cells' indentations, mm
    # With the m nearest cells in contact, d = (target + their gaps' sum) / m; the first m whose d
    # does not reach the next cell's gap is the balance.
    candidates = (target + np.cumsum(gaps)) / np.arange(1, gaps.size + 1)
    next_gap = np.append(gaps[1:], np.inf)
    d = float(candidates[int(np.argmax(candidates <= next_gap))])
    saturated = d > thickness_mm
    d = min(d, thickness_mm)
    return d, float(np.count_nonzero(gaps < d) * cell_area_mm2), saturated
