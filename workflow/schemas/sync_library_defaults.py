"""Regenerate the library sections of config.schema.yaml from the modules' *_DEFAULTS (developer tool).

Run ``python workflow/schemas/sync_library_defaults.py`` after a step module changes its DEFAULTS;
tests/unit/test_analysis_config.py fails until the schema mirrors them again. Rewrites only the block between the
``# ---- generated`` and ``# ---- end generated`` marker lines; per-key refinements (enums, ranges, unions) are in
``REFINE``.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import yaml

SCHEMA = Path(__file__).resolve().parent / "config.schema.yaml"
BEGIN = "  # ---- generated from the library DEFAULTS"
END = "  # ---- end generated"
GRID_KEYS = {"volume", "radiographs", "sfm_dir", "init", "compositor", "mip", "poses", "views", "seed", "device"}

REFINE: dict[tuple[str, str], dict[str, Any]] = {
    ("preprocessing", "voxel_size_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("preprocessing", "grid"): {"type": ["integer", "array", "null"], "minimum": 2,
                                "items": {"type": "integer", "minimum": 2}, "minItems": 3, "maxItems": 3},
    ("preprocessing", "intensity"): {"enum": ["attenuation", "window", "mu", "hu"]},
    ("preprocessing", "window"): {"type": ["string", "array"], "items": {"type": "number"}, "minItems": 2,
                                  "maxItems": 2},
    ("preprocessing", "denoise"): {"enum": [None, "tv", "bilateral"]},
    ("preprocessing", "mask"): {"enum": [None, "otsu", "convex_hull"]},
    ("radiographs", "camera"): {"enum": ["parallel", "cone"]},
    ("radiographs", "orbit"): {"enum": ["circular", "sphere"]},
    ("radiographs", "sphere_sampling"): {"enum": ["fibonacci", "stratified"]},
    ("radiographs", "pixel_spacing_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "parallel_distance_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "arc_deg"): {"type": ["number", "null"], "exclusiveMinimum": 0, "maximum": 360},
    ("radiographs", "isocenter_mm"): {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 3,
                                      "maxItems": 3},
    ("radiographs", "n_views"): {"type": "integer", "minimum": 1},
    ("radiographs", "detector_width"): {"type": "integer", "minimum": 1},
    ("radiographs", "detector_height"): {"type": "integer", "minimum": 1},
    ("sfm", "pitch_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("sfm", "matching"): {"enum": ["exhaustive", "sequential", "spatial"]},
    ("sfm", "mapper"): {"enum": ["incremental", "global"]},
    ("sfm", "pose_prior"): {"enum": ["none", "position", "refine", "refine_prior", "isocentric"]},
    ("sfm", "design_sigma_deg"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("sfm", "isocentre_sigma_mm"): {"type": "number", "minimum": 0},
    ("sfm", "isocentric_loss_px"): {"type": "number", "exclusiveMinimum": 0},
    ("sfm", "orbit_jitter_mm"): {"type": "number", "minimum": 0},
    ("sfm", "fuse_harmonics"): {"type": "integer", "minimum": 0},
    ("train", "supervision"): {"enum": ["line_integral", "transmission"]},
    ("train", "iterations"): {"type": "integer", "minimum": 1},
    ("train", "n_init"): {"type": "integer", "minimum": 1},
    ("baselines", "fbp_filters"): {"type": "array",
                                   "items": {"enum": ["ramp", "shepp-logan", "cosine", "hamming", "hann"]}},
    ("baselines", "split"): {"enum": ["train", "val", "test"]},
    ("baselines", "sart_max_iterations"): {"type": "integer", "minimum": 1},
}


def _type(v: Any) -> dict[str, Any]:
    if v is None:
        return {}
    for py, js in ((bool, "boolean"), (int, "integer"), (float, "number"), (str, "string"), (list, "array"),
                   (dict, "object")):
        if isinstance(v, py):
            return {"type": js}
    return {}


def _section(name: str, defaults: dict[str, Any], skip: set[str], description: str) -> dict[str, Any]:
    props: dict[str, Any] = {}
    for key, val in defaults.items():
        if key in skip:
            continue
        if isinstance(val, dict) and val:
            props[key] = {"type": "object", "additionalProperties": False, "default": {},
                          "properties": _section(name, val, set(), "")["properties"]}
        else:
            props[key] = {**_type(val), "default": val}
            if (name, key) in REFINE:
                props[key].pop("type", None)
                props[key].update(REFINE[(name, key)])
    out = {"type": "object", "additionalProperties": False, "properties": props}
    if description:
        out["description"] = description
    return out


def generated_block() -> str:
    from ctsplat.baselines import BASELINES_DEFAULTS
    from ctsplat.projector import RADIOGRAPHS_DEFAULTS
    from ctsplat.sfm import SFM_DEFAULTS
    from ctsplat.train import TRAIN_DEFAULTS
    from ctsplat.volume import PREPROCESSING_DEFAULTS

    defs = {
        "preprocessing": _section("preprocessing", PREPROCESSING_DEFAULTS, set(),
                                  "ctsplat.volume.PREPROCESSING_DEFAULTS"),
        "radiographs": _section("radiographs", RADIOGRAPHS_DEFAULTS, set(), "ctsplat.projector.RADIOGRAPHS_DEFAULTS"),
        "sfm": _section("sfm", SFM_DEFAULTS, set(), "ctsplat.sfm.SFM_DEFAULTS"),
        "train": _section("train", TRAIN_DEFAULTS, GRID_KEYS,
                          "ctsplat.train.TRAIN_DEFAULTS without the keys the grid sets per run"),
        "baselines": _section("baselines", BASELINES_DEFAULTS, {"n_views"},
                              "ctsplat.baselines.BASELINES_DEFAULTS without n_views (the grid's view counts)"),
    }
    return textwrap.indent(yaml.safe_dump(defs, sort_keys=False, default_flow_style=None, width=110), "  ")


def main() -> None:
    text = SCHEMA.read_text()
    lines = text.splitlines(keepends=True)
    b = next(i for i, line in enumerate(lines) if line.startswith(BEGIN))
    e = next(i for i, line in enumerate(lines) if line.startswith(END))
    SCHEMA.write_text("".join(lines[: b + 1]) + generated_block() + "".join(lines[e:]))
    print(f"updated {SCHEMA}")


if __name__ == "__main__":
    main()
