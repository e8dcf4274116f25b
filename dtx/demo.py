"""``dtx demo``: the main job on the simulated scene, end to end, as an operator would run it.

1. collect 1,200 grasps (2,400 pairs) with ``launch/collect_sim.yaml`` — the paper had 289
   (``--grasps 289``); simulated grasps are cheap, 4x the data gives the model more to
   learn from, and a 360-pair test split tells it from the baseline with room to spare;
2. calibrate the depth cameras and place the objects from the session's own training touches
   (``dtx calibrate touches``), and cut its depth-maps again at those places (``dtx dataset
   redepth --calibration``), the contact library made beside the cut;
   train the cGAN on those with ``configs/quick.yaml``, its prior as sure of the geometry as
   the calibration allows (dataset.touch_calibration.CALIBRATED_POSE_SIGMA_MM);
3. evaluate it like the paper, at the paper's point densities too (the test split's depth-maps
   made again from thinned model clouds), and print the table; figures go to ``OUT/figures``.

Each step is the real command, run as a process; a step whose result is already there
(a complete dataset, a finished checkpoint) is continued or skipped, so running the demo
again resumes it. Only the code that began a demo resumes it: a calibration or a library made
by other code would be kept unseen or refused halfway.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

REAL_PRESSES = "assets/gelsight/ball_presses.npz"
LIBRARY_SAMPLES = 1200
# The touch calibration (and a redepth that must place the objects again) shares its touches out
# among this many processes: one per core of the 2-core machine the demo is sized for.
JOBS = 2
SESSION_TOPICS = "[/collector/sample,/perception/object_cloud,/perception/registration_frames,/perception/depth_map,/arm/state,/gripper/state]"


# The width a shown command wraps at, as a shell continues a line (a log stays readable).
COMMAND_WIDTH = 100


def shown_command(command: list[str]) -> str:
    """``dtx COMMAND...`` as a shell prompt shows it, wrapped with ``\\`` before
    ``COMMAND_WIDTH`` characters (an argument longer than that keeps a line of its own)."""
    prompt, indent = "$ dtx", "   "
    lines = [prompt]
    for arg in command:
        if len(lines[-1]) + 1 + len(arg) > COMMAND_WIDTH - 2 and lines[-1] not in (prompt, indent):
            lines[-1] += " \\"
            lines.append(indent)
        lines[-1] += f" {arg}"
    return "\n".join(lines)


def _run(step: str, command: list[str], capture: bool = False) -> str:
    print(f"\n== {step}\n{shown_command(command)}", flush=True)
    started = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "dtx.cli", *command], text=True, stdout=subprocess.PIPE if capture else None
    )
    if result.returncode != 0:
        raise SystemExit(f"demo: step '{step}' failed (exit {result.returncode})")
    print(f"== {step}: done in {time.monotonic() - started:.0f} s", flush=True)
    return result.stdout or ""


def _start(step: str, command: list[str]) -> Callable[[], None]:
    """``command`` started as a process beside the steps that follow; returns the wait for it,
    which fails the demo as :func:`_run` does."""
    print(f"\n== {step} (beside the next step)\n{shown_command(command)}", flush=True)
    started = time.monotonic()
    process = subprocess.Popen([sys.executable, "-m", "dtx.cli", *command])

    def wait() -> None:
        if process.wait() != 0:
            raise SystemExit(f"demo: step '{step}' failed (exit {process.returncode})")
        print(f"== {step}: done in {time.monotonic() - started:.0f} s", flush=True)

    return wait


# The paper's SSIM at each point density it tried (points/cm^3).
PAPER_DENSITY_SSIM = {1: "0.8238", 10: "0.8278", 20: "0.8478", 40: "0.8480", 80: "0.8476"}

# A table row: (figure, this run's value, the paper's value or "").
Row = tuple[str, str, str]


def paper_table(evaluation: dict) -> str:
    """The paper's comparison, with its figures beside ours."""
    rows = [
        *_headline_rows(evaluation),
        *_contact_rows(evaluation.get("contact", {})),
        *_object_rows(evaluation.get("objects", {})),
        *_density_rows(evaluation.get("density", [])),
    ]
    width = max(len(r[0]) for r in rows)
    lines = [f"{'':{width}}  {'this run':>18}  {'paper':>14}"]
    lines += [f"{name:{width}}  {ours:>18}  {paper:>14}" for name, ours, paper in rows]
    return "\n".join(lines)


def _headline_rows(evaluation: dict) -> list[Row]:
    """SSIM against the baseline, its ratio and p-values (PSNR after the ratio when measured),
    and the template match."""
    template = evaluation.get("template_match", {})
    rows = [
        (
            "SSIM, estimate vs ground truth",
            f"{evaluation['ssim_model_mean']:.3f} ± {evaluation['ssim_model_se']:.4f}",
            "0.84 ± 0.0056",
        ),
        (
            "SSIM, baseline (15 random ground truths)",
            f"{evaluation['ssim_baseline_mean']:.3f} ± {evaluation['ssim_baseline_se']:.4f}",
            "0.80 ± 0.0036",
        ),
        ("dissimilarity ratio (1-SSIM model)/(1-SSIM base)", f"{evaluation['dissimilarity_ratio']:.2f}", "0.80"),
        ("p-value, Wilcoxon signed-rank", f"{evaluation['p_value_wilcoxon']:.2e}", "< 0.05"),
        ("p-value, paired t", f"{evaluation['p_value_t']:.2e}", ""),
        ("template match score (TM_CCOEFF_NORMED), mean", f"{template.get('score_mean', float('nan')):.3f}", ""),
        ("template match distance, median (px)", f"{template.get('distance_px_median', float('nan')):.1f}", ""),
    ]
    if "psnr" in evaluation:
        rows.insert(
            3,
            (
                "PSNR (dB), estimate / baseline",
                f"{evaluation['psnr']['psnr_db_model_mean']:.2f} / {evaluation['psnr']['psnr_db_baseline_mean']:.2f}",
                "",
            ),
        )
    return rows


def _contact_rows(contact: dict) -> list[Row]:
    """SSIM on the contact windows alone, when the evaluation measured it."""
    if "ssim_model_mean" not in contact:
        return []
    return [
        (
            f"SSIM on contact windows only ({contact['n']} pairs), model / baseline",
            f"{contact['ssim_model_mean']:.3f} / {contact['ssim_baseline_mean']:.3f}",
            "",
        ),
        (
            "  its ratio (p Wilcoxon)",
            f"{contact['dissimilarity_ratio']:.2f} ({contact['p_value_wilcoxon']:.1e})",
            "",
        ),
    ]


def _object_rows(objects: dict) -> list[Row]:
    """Per object: SSIM of model and baseline, and their dissimilarity ratio."""
    return [
        (
            f"  {name} ({stats['n']} pairs): SSIM model / baseline, ratio",
            f"{stats['ssim_model_mean']:.3f} / {stats['ssim_baseline_mean']:.3f}, {stats['dissimilarity_ratio']:.2f}",
            "",
        )
        for name, stats in objects.items()
    ]


def _density_rows(density: list[dict]) -> list[Row]:
    """SSIM at each point density (beside the paper's where it tried that density), and on the
    contact windows alone when measured."""
    rows = []
    for row in density:
        psnr = f" (PSNR {row['psnr_db_mean']:.1f} dB)" if "psnr_db_mean" in row else ""
        rows.append(
            (
                f"SSIM at {row['points_per_cm3']:g} points/cm^3{psnr}",
                f"{row['ssim_mean']:.4f} ± {row['ssim_se']:.4f}",
                PAPER_DENSITY_SSIM.get(row["points_per_cm3"], ""),
            )
        )
        if "contact_ssim_mean" in row:
            against_empty = ""
            if "contact_p_better_than_empty" in row:
                against_empty = (
                    f" (empty map {row['empty_contact_ssim_mean']:.4f}, p {row['contact_p_better_than_empty']:.1e})"
                )
            rows.append(
                (
                    "  on contact windows only",
                    f"{row['contact_ssim_mean']:.4f} ± {row['contact_ssim_se']:.4f}{against_empty}",
                    "",
                )
            )
    return rows


def _collected(session: Path, args: argparse.Namespace) -> Path:
    """The simulated session, collected (or resumed) and checked."""
    collect = ["launch", "launch/collect_sim.yaml", f"out:={session}", f"grasps:={args.grasps}"]
    collect += [f"seed:={args.seed}", f"record_topics:={SESSION_TOPICS}"]
    if (session / "manifest.jsonl").exists():
        collect.append("resume:=true")
    _run("1/4 collect (Algorithm 1 on the simulated scene; the session ends with its dataset's check)", collect)
    return session


def _calibrated(session: Path, out: Path, library_samples: int, seed: int) -> tuple[Path, Path | None]:
    """The session with its depth-maps cut again by cameras calibrated from its own training
    touches (a calibration already there is kept), and the contact library of
    ``library_samples`` pairs (None for none), made beside the cut: each is one process, and the
    demo's machine has two cores."""
    calibration, calibrated, library = out / "calibration", out / "session_calibrated", out / "library"
    if not (calibration / "report.json").exists():
        _run(
            "1/4 calibrate the cameras from the session's training touches",
            ["calibrate", "touches", str(session), "--out", str(calibration), "--force", "--jobs", str(JOBS)],
        )
    library_made = (
        _start(
            "2/4 contact library (the simulated world's spheres, cylinders, edges, textures)",
            ["dataset", "library", str(library), "--samples", str(library_samples), "--seed", str(seed)],
        )
        if library_samples
        else None
    )
    _run(  # resumes a torn run: the samples already there are kept
        "1/4 the session's depth-maps cut again with the calibrated cameras",
        ["dataset", "redepth", str(session), "--calibration", str(calibration), "--out", str(calibrated)]
        + ["--jobs", str(JOBS)],
    )
    if library_made is None:
        return calibrated, None
    library_made()
    return calibrated, library


def begun_by_other_code(out: Path) -> str | None:
    """The code version that began the demo in ``out`` (its session's ``dataset.json``) where it
    is not this checkout's, else None (nothing there yet, or this code's own run)."""
    from dataset.reader import read_info
    from dataset.records import code_version

    info = out / "session" / "dataset.json"
    if not info.exists():
        return None
    begun = read_info(info).code_version
    return begun if begun != code_version() else None


def cmd_demo(args: argparse.Namespace) -> int:
    from dataset.records import code_version
    from dataset.touch_calibration import CALIBRATED_POSE_SIGMA_MM
    from models.real_presses import real_press_table
    from models.uncertainty import uncertainty_table
    from perception.density import DENSER_PER_CM3, PAPER_DENSITIES_PER_CM3

    out = Path(args.out)
    begun = begun_by_other_code(out)
    if begun is not None:
        print(
            f"error: {out} holds a demo begun by {begun}, this is {code_version()}: remove {out} "
            "(or give --out DIR) to run this code's demo",
            file=sys.stderr,
        )
        return 1
    train_dir, figures = out / "train", out / "figures"
    session, library = _calibrated(_collected(out / "session", args), out, args.library_samples, args.seed)
    train = ["train", str(session), "--config", args.config, "--out", str(train_dir)]
    train += ["--session-pose-sigma-mm", f"{CALIBRATED_POSE_SIGMA_MM:g}"]
    if library is not None:
        train += ["--library", str(library)]
    if (train_dir / "checkpoint.pt").exists():
        train.append("--resume")
    _run("3/4 train the cGAN", train)
    report = _run(
        "4/4 evaluate like the paper, at its point densities and denser, and on real GelSight presses it never saw",
        [
            "evaluate",
            str(train_dir / "checkpoint.pt"),
            str(session),
            "--json",
            "--figures",
            str(figures),
            "--real-presses",
            REAL_PRESSES,
            "--density",
            *[f"{d:g}" for d in [*PAPER_DENSITIES_PER_CM3, *DENSER_PER_CM3]],
        ],
        capture=True,
    )
    evaluation = json.loads(report)
    (out / "evaluation.json").write_text(json.dumps(evaluation, indent=2) + "\n")
    print("\n" + paper_table(evaluation))
    if "uncertainty" in evaluation:
        print("\nthe served uncertainty on the test split\n" + "\n".join(uncertainty_table(evaluation["uncertainty"])))
    print("\n" + real_press_table(evaluation["real_presses"]))
    print(f"\nfigures in {figures}; full results in {out / 'evaluation.json'}")
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser("demo", help="collect, train and evaluate on the simulated scene")
    demo.add_argument("--out", default="out/demo")
    demo.add_argument("--grasps", type=int, default=1200, help="grasps to collect (the paper's session: 289)")
    demo.add_argument(
        "--library-samples",
        type=int,
        default=LIBRARY_SAMPLES,
        help=f"contact-library pairs trained beside the session (default {LIBRARY_SAMPLES}; "
        "0: the session alone, as the paper)",
    )
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--config", default="configs/quick.yaml")
    demo.set_defaults(func=cmd_demo)
