"""The dataset card (``README.md``) of a Hugging Face export: YAML front matter the Hub and
``datasets.load_dataset`` read (the splits' files, the features, the licence), then what a reader
needs to use the pairs: units, frames, the columns, the splits, each session's scene and the
licence of the meshes its depth-maps were cut from."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import datasets
from datasets.info import DatasetInfo, DatasetInfosDict
from datasets.splits import SplitDict, SplitInfo
from huggingface_hub import DatasetCardData

from dataset.records import DatasetInfo as SessionInfo
from workcell.scene import SceneError, load_scene, resolve_path

# The pairs are the project's output; the YCB meshes they are cut from ask for attribution
# (CC BY 4.0), which this licence carries on.
LICENSE = "cc-by-4.0"
_MAX_ATTRIBUTION_CHARS = 2000


@dataclasses.dataclass(frozen=True)
class SessionSummary:
    """What the card says of one exported session."""

    name: str
    fingerprint: str  # what a checkpoint trained on the session records of it
    checksum: str  # `dtx dataset checksum` of the session
    info: SessionInfo
    objects: tuple[str, ...]
    counts: dict[str, int]  # pairs per Hugging Face split


_COLUMNS = (
    ("sample_id", "string", "the pair's id in its session (its files there: `tactile/<id>.png`, ...)"),
    ("session", "string", "the session the pair comes from (table below)"),
    ("object", "string", "the touched object's name in the session's scene"),
    ("grasp_id", "int64", "the grasp within the session; both fingers of a grasp share it"),
    ("finger", "string", "`left` or `right`: the gel (frame `gel_left` / `gel_right`) the pair was felt with"),
    ("tactile", "image", "GelSight image, 8-bit RGB (levels 0..255), as captured"),
    (
        "tactile_diff",
        "image",
        "the image less the session's no-contact background, plus 128 (8-bit RGB; 128 = no change)",
    ),
    (
        "depth_map_m",
        "float32 H x W",
        "contact depth-map in metres: rows along gel z, columns along gel x; each bin holds y, the "
        "object's distance from the gel surface (> 0 free, < 0 pressing in); NaN or +inf: empty bin",
    ),
    ("grasp_pose_world", "4 x float64", "the grasp pose in `world`: x, y, z (m) and θz (rad)"),
    ("gel_to_world", "4 x 4 float64 or null", "the gel's pose in `world`, as the arm measured it"),
    (
        "model_to_world",
        "4 x 4 float64 or null",
        "the object model's registered pose in `world` (before centring between the gels)",
    ),
    ("model_to_gel", "4 x 4 float64 or null", "the object model in the gel frame, as the depth-map was cut"),
    ("registration_fitness", "float64", "the object's registration fitness (fraction of its cloud matched)"),
)


def card_yaml(features: datasets.Features, counts: dict[str, int]) -> str:
    """The front matter: one default config whose splits are the ``data/<split>-*`` shards, the
    features and split sizes, the licence."""
    splits = [name for name, count in counts.items() if count]
    card = DatasetCardData(
        license=LICENSE,
        pretty_name="dtx tactile pairs",
        task_categories=["image-to-image"],
        tags=["robotics", "tactile", "gelsight", "depth-map"],
        configs=[
            {
                "config_name": "default",
                "data_files": [{"split": name, "path": f"data/{name}-*"} for name in splits],
            }
        ],
    )
    split_dict = SplitDict()
    for name in splits:
        split_dict.add(SplitInfo(name=name, num_examples=counts[name]))
    DatasetInfosDict({"default": DatasetInfo(features=features, splits=split_dict)}).to_dataset_card_data(card)
    return card.to_yaml()


def dataset_card(features: datasets.Features, sessions: list[SessionSummary]) -> str:
    """The whole ``README.md``."""
    counts = {name: sum(s.counts.get(name, 0) for s in sessions) for name in ("train", "validation", "test")}
    info = sessions[0].info  # what every session shares (the export refuses others)
    parts = [
        f"---\n{card_yaml(features, counts).strip()}\n---\n",
        f"# dtx tactile pairs: {', '.join(s.name for s in sessions)}\n",
        f"{sum(counts.values())} GelSight tactile images, each paired with the contact depth-map of the same "
        f"touch, from {len(sessions)} session(s) of dtx (Deep Tactile Experience): "
        f"{info.image_height} x {info.image_width} pixels and bins a pair.\n",
        "```python\nfrom datasets import load_dataset\n\n"
        'pairs = load_dataset("path/to/this/directory")  # splits train, validation, test\n'
        'pair = pairs["train"].with_format("numpy")[0]   # tactile: H x W x 3 uint8, depth_map_m: H x W float32\n'
        "```\n\n"
        "numpy's formatter hands every float as float32; the poses are float64 in the files: read them with "
        '`with_format("numpy", dtype="float64")` (or the default Python format) to have them exactly.\n',
        _units_and_frames(info),
        _columns(),
        _splits(sessions, counts),
        _sessions(sessions),
        _licence(sessions),
    ]
    return "\n".join(parts)


def _units_and_frames(info: SessionInfo) -> str:
    return (
        "## Units and frames\n\n"
        "SI units: metres and radians; images 8-bit, levels 0..255. Frames are right-handed: `world` (the "
        "table), `gel_left` and `gel_right` (one per finger): origin at the centre of the gel surface, x and z in "
        "the surface, y along its outward normal, so y > 0 is free space and y < 0 indents the elastomer. A "
        "4 x 4 matrix `A_to_B` maps homogeneous points of frame A to frame B: it is A's pose in B (`model` is "
        "the object's mesh frame).\n\n"
        "The depth-map is what a camera looking at the gel from the object's side would see: row 0 at gel "
        f"z = -half, column 0 at gel x = -half. Shared by every pair: depth range for normalisation "
        f"{list(info.depth_range_m)} m (near, far), bins holding `{info.depth_map_method}` (`surface`: the "
        "object's surface at the bin's centre; `nearest_point`: the least y of the bin's points). Each session's "
        "crop volume, the gel-frame box a map covers, is in the sessions' table.\n"
    )


def _columns() -> str:
    rows = "\n".join(f"| `{name}` | {kind} | {text} |" for name, kind, text in _COLUMNS)
    return f"## Columns\n\n| column | type | meaning |\n|---|---|---|\n{rows}\n"


def _splits(sessions: list[SessionSummary], counts: dict[str, int]) -> str:
    empty = [name for name, count in counts.items() if not count]
    return (
        "## Splits\n\n"
        "train, validation and test are dtx's own split, as `dtx train` makes it of these sessions "
        "(`dataset/splits.py`): each session's grasps, ordered by a SHA-256 of its split seed and "
        "`object/grasp_id`, cut at 70 % and 85 %, so both fingers of a grasp lie in one split; a grasp that "
        "repeats another session's contact joins that grasp's split. `validation` is dtx's `val`. Pairs per "
        "split: "
        + ", ".join(f"{name} {count}" for name, count in counts.items())
        + (f" (left out, having none: {', '.join(empty)})" if empty else "")
        + ".\n"
    )


def _sessions(sessions: list[SessionSummary]) -> str:
    rows = "\n".join(
        f"| `{s.name}` | {sum(s.counts.values())} | {s.counts.get('train', 0)} / {s.counts.get('validation', 0)} / "
        f"{s.counts.get('test', 0)} | {s.info.scene or 'not recorded'} | {', '.join(s.info.effects) or 'none'} | "
        f"{_crop(s.info)} | {s.info.split_seed} | `{s.fingerprint}` | `{s.checksum}` |"
        for s in sessions
    )
    return (
        "## Sessions\n\n"
        "Crop: the gel-frame box (x, y, z) a depth-map covers. Fingerprint: what a dtx checkpoint trained on the "
        "session records of it. Checksum: `dtx dataset checksum` of the session (what it holds, capture times "
        "and code version left out).\n\n"
        "| session | pairs | train / validation / test | scene | simulated effects | crop (mm) | split seed "
        "| fingerprint | checksum |\n"
        f"|---|---|---|---|---|---|---|---|---|\n{rows}\n"
    )


def _crop(info: SessionInfo) -> str:
    return "not recorded" if info.depth_crop_m is None else " x ".join(f"{v * 1000:.2f}" for v in info.depth_crop_m)


def _licence(sessions: list[SessionSummary]) -> str:
    """The pairs' licence, and each mesh's attribution as its folder states it."""
    attributions: dict[Path, list[str]] = {}
    unknown = []
    for session in sessions:
        meshes = _meshes(session)
        if meshes is None:
            unknown.append(session.name)
            continue
        for obj, mesh in meshes.items():
            attributions.setdefault(mesh.parent / "ATTRIBUTION.md", []).append(f"{obj} ({mesh.name})")
    lines = [
        "## Scene, meshes and licence\n",
        "The pairs are licensed CC BY 4.0. What their depth-maps and poses are made from, and its licence:\n",
    ]
    for path, objects in attributions.items():
        try:
            text = path.read_text()[:_MAX_ATTRIBUTION_CHARS].strip()
        except OSError:
            text = "(no attribution file beside the meshes: their licence is not known here)"
        quoted = "\n".join(f"> {line}" if line else ">" for line in text.splitlines())
        lines.append(f"- {', '.join(sorted(set(objects)))}:\n\n{quoted}\n")
    if unknown:
        lines.append(
            f"- the objects of {', '.join(unknown)}: their scene names no meshes here (analytic shapes, or a scene "
            "file this machine lacks).\n"
        )
    lines.append("The code that made them, dtx, is MIT-licensed.\n")
    return "\n".join(lines)


def _meshes(session: SessionSummary) -> dict[str, Path] | None:
    """Each object's mesh as the session's scene names it; None when the scene cannot be read."""
    try:
        scene = load_scene(session.info.scene)
    except (SceneError, OSError, ValueError):  # a synthetic session's "scene" is a description
        return None
    meshes = {o.name: resolve_path(o.mesh) for o in scene.objects if o.mesh and o.name in session.objects}
    return meshes or None
