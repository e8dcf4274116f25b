"""``dtx calibrate uncertainty``: a checkpoint written with the floor of a lab's own GelSight
(models.sensor_floor), fitted on the lab's ball presses."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from models.checkpoint import load_checkpoint, load_generator, save_atomic
from models.errors import ModelConfigError
from models.real_presses import evaluate_real_presses
from models.sensor_floor import fit_sensor_floor, presses_digest
from models.uncertainty import SensorFloor, ServedUncertainty, pixel_error_levels


def calibrate_sensor_floor(
    checkpoint: str | os.PathLike[str],
    presses: str | os.PathLike[str],
    out: str | os.PathLike[str],
    force: bool = False,
    **press_options: Any,
) -> dict[str, Any]:
    """Write ``checkpoint`` with the floor of the sensor whose ``presses`` these are to ``out``
    (atomically; an existing ``out`` only with ``force``). ``press_options``: scene,
    ball_radius_mm, mm_per_px as models.real_presses.evaluate_real_presses takes them. Returns
    the report: the floor, and u on the presses as the checkpoint served it and with the floor
    fitted on the other presses. ModelConfigError for a checkpoint without an uncertainty."""
    target = Path(out)
    if target.exists() and not force:
        raise FileExistsError(f"{target} exists; give --force to replace it")
    generator, depth_range_m = load_generator(checkpoint)
    if generator.uncertainty is None:
        raise ModelConfigError(f"{checkpoint} serves no uncertainty to add a floor to (dtx fit-serving fits one)")
    result, images = evaluate_real_presses(generator, depth_range_m, presses, **press_options)
    own = images["uncertainty_own"]
    source = {"file": Path(presses).name, "presses": len(own), "sha256": presses_digest(presses)}
    floor = SensorFloor(fit_sensor_floor(pixel_error_levels(images["model"], images["truth"]), own), source)
    served = generator.uncertainty
    state = load_checkpoint(checkpoint)
    state["uncertainty"] = ServedUncertainty(served.net, served.calibration, served.config, floor).to_state()
    save_atomic(state, target)
    return {
        "checkpoint": str(checkpoint),
        "out": str(target),
        "presses": source,
        "floor_mean_levels": float(floor.levels.mean()),
        "floor_max_levels": float(floor.levels.max()),
        "served_before": result["uncertainty"],
        "leave_one_out": result.get("uncertainty_lab_floor"),
    }
