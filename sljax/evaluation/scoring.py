"""Evaluation of a predictor over a dataset: per-scene and pooled metrics, reports, pictures.

A predictor is anything called as `predictor(left, right, calib=None) -> {"disparity": ...}`
with attributes `model_name`, `is_sl`, `mode` and a `describe()` line: the network predictors
of sljax.inference and the SGBM baseline of sljax.inference.sgbm.

Regions: "full" = every pixel with finite ground truth; "seg" = those inside mask0 (when the
scene has one).

SCARED keyframes imported by `sljax import-scared` (meta.json "source": "SCARED" with the
original frame kept) are also scored as the SCARED toolkit scores them (sljax.capture.scared):
the predicted disparity is mapped back to the original, unrectified and distorted left view
and compared with the keyframe's own depth map there; depth MAE in mm per keyframe, keyframes
whose ground truth covers under 10% of the pixels excluded, and the mean over the scored
keyframes. Depth statistics are added when the scene has a calibration. For models that
predict patterns, pattern accuracy is measured against sl0 (and sl1 for two-view models) over
known pattern pixels; for unet-sl the evaluated disparity is the correlation of its predicted
patterns (sljax.corr), as in the paper.
"""

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from sljax.capture import scared
from sljax.corr.uncertainty import pattern_uncertainty
from sljax.data.checks import no_usable_disparity
from sljax.data.pfm import read_pfm, write_pfm
from sljax.data.scene import present_parts
from sljax.depth.geometry import check_calib_size
from sljax.errors import SljaxError
from sljax.evaluation import metrics
from sljax.io import files, tables
from sljax.io.pictures import Panel, save_panels

REGIONS = ("full", "seg")
_LEFT_FILES = {"disp0.pfm", "mask0.png", "sl0", "calib.txt", "meta.json"}
_HEADERS = {
    "mae": "MAE px", "iqr": "IQR px", "rms": "RMS px", "a90": "A90 px", "bad_0.5": "bad-0.5 %",
    "bad_1": "bad-1 %", "bad_2": "bad-2 %", "bad_3": "bad-3 %", "d1": "D1 %",
    "invalid_pred": "invalid %", "n_pixels": "pixels", "depth_mae_mm": "depth MAE mm",
    "depth_iqr_mm": "depth IQR mm",
}
NO_GT_NOTE = "no scene has ground-truth disparity (disp0.pfm): no metrics could be computed"


def check_out_dir(out: str | os.PathLike, overwrite: bool) -> Path:
  """The output folder, checked, not created (`evaluate` moves it in whole at the end); refuses a
  non-empty one unless overwrite."""
  out = files.check_output_folder(out, overwrite, must_be_empty=True)
  return out


def _load(source, i: int):
  """Scene i without raw captures (not needed here) when the source is a folder."""
  paths = getattr(source, "paths", None)
  if paths is not None and hasattr(source, "get"):
    parts = {p for p, present in present_parts(paths[i]).items()
             if p != "raw" and (p == "im" or _LEFT_FILES & set(present))}
    return source.get(i, parts=parts | {"im"})
  return source[i]


def _scene_label(source, i: int, scene) -> str:
  name = source.name(i) if hasattr(source, "name") else scene.name
  return str(name)


def _scene_where(source, i: int, label: str) -> str:
  paths = getattr(source, "paths", None)
  return f"scene {paths[i]}" if paths is not None else f"scene {label}"


def _disp_range(gt: np.ndarray | None, pred: np.ndarray) -> tuple[float, float]:
  """One colour range for truth and prediction: the truth's finite range, else the prediction's."""
  for a in (gt, pred):
    if a is not None:
      f = a[np.isfinite(a)]
      if f.size:
        lo, hi = float(f.min()), float(f.max())
        return lo, hi if hi > lo else lo + 1.0
  return 0.0, 1.0


def _figure(path: Path, label: str, scene, out: dict[str, np.ndarray], title: str) -> None:
  pred = out["disparity"]
  gt = scene.disp0
  lo, hi = _disp_range(gt, pred)
  panels = [Panel("left (im0)", scene.im0), Panel("right (im1)", scene.im1)]
  if gt is not None:
    panels.append(Panel("ground truth", gt, cmap="turbo", vmin=lo, vmax=hi, label="px"))
  panels.append(Panel("prediction", pred, cmap="turbo", vmin=lo, vmax=hi, label="px"))
  if gt is not None:
    with np.errstate(invalid="ignore"):  # inf - inf where both are unknown
      err = np.where(np.isfinite(gt), np.abs(pred - gt), np.nan)
    finite = err[np.isfinite(err)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    panels.append(Panel("absolute error", err, cmap="magma", vmin=0.0, vmax=max(top, 1e-3),
                        label="px"))
  if "patterns" in out:
    p = out["patterns"]
    t = p.shape[-1]
    for k in sorted({0, t // 2, t - 1}):
      panels.append(Panel(f"pattern {k} (p lit)", p[..., k]))
    if "uncertainty" in out:
      panels.append(Panel("pattern uncertainty (left)", out["uncertainty"], cmap="viridis",
                          vmin=0.0, vmax=1.0))
    if "confidence" in out:
      panels.append(Panel("confidence", out["confidence"], cmap="viridis", vmin=0.0, vmax=1.0))
  # Disparity models fit one row (inputs, truth, prediction, error); SL models wrap at 4.
  save_panels(path, panels, ncols=len(panels) if len(panels) <= 5 else 4,
              title=f"{label} - {title}")


def _uncertainty(out: dict[str, np.ndarray]) -> np.ndarray:
  """Pixel-wise uncertainty of the left view's predicted patterns (aligned with the disparity)."""
  return np.asarray(pattern_uncertainty(out["patterns"]), dtype=np.float32)


def _scared_row(source, i: int, scene, disparity: np.ndarray, where: str
                ) -> dict[str, Any] | None:
  """scared_toolkit-style error in the original frame, for imported SCARED keyframes."""
  paths = getattr(source, "paths", None)
  if paths is None or scene.meta.get("source") != "SCARED" or scene.calib is None:
    return None
  gt_path = paths[i] / scared.ORIGINAL_DEPTH
  if not gt_path.exists() or "original" not in scene.meta:
    return {"note": f"no {scared.ORIGINAL_DEPTH} / meta 'original' (imported before they were "
                    "kept): re-import the keyframe to score it in the original frame"}
  original = scared.read_original(scene.meta, where)
  gt = read_pfm(gt_path)
  if gt.shape != original["size"]:
    raise SljaxError(f"{where}: {scared.ORIGINAL_DEPTH} is {gt.shape[1]}x{gt.shape[0]}, meta.json "
                     f"'original' says {original['size'][1]}x{original['size'][0]}")
  pred = scared.original_frame_depth(disparity, scene.calib, original)
  return scared.keyframe_error(gt, pred)


def check_mae(result: dict[str, Any], gt: np.ndarray, where: str) -> None:
  """SljaxError naming the scene when its MAE is no error a disparity can have: not finite
  although the truth is known somewhere, or more than the image's width (values no match can
  have, in the truth or in the prediction)."""
  mae, width = result["mae"], gt.shape[1]
  if result["n_pixels"] == 0 or (math.isfinite(mae) and mae <= width):
    return
  with np.errstate(invalid="ignore"):
    beyond = int(np.count_nonzero(np.isfinite(gt) & (np.abs(gt) > width)))
  culprit = (f"disp0.pfm holds {beyond} known disparities beyond the image's width ({width} px; "
             "unknown pixels must be inf or NaN)" if beyond else
             "the prediction is not finite wherever the truth is known" if not math.isfinite(mae)
             else f"the prediction holds disparities beyond the image's width ({width} px)")
  raise SljaxError(f"{where}: the mean absolute error would be {mae:g} px: {culprit}")


def evaluate(predictor, source, indices: list[int] | None = None, *, out_dir: Path | None = None,
             save_predictions: bool = False, figures: bool = False,
             progress: bool = True, info: dict[str, Any] | None = None) -> dict[str, Any]:
  """Runs the predictor over the scenes and returns the report (written when out_dir is set)."""
  kwargs = dict(save_predictions=save_predictions, figures=figures, progress=progress, info=info)
  if out_dir is None:
    return _evaluate(predictor, source, indices, None, **kwargs)
  # Written into a hidden folder and moved in once every scene is scored: a failure or Ctrl-C
  # leaves out_dir as it was (absent stays absent, --overwrite's earlier files stay).
  with files.staged(out_dir) as stage:
    return _evaluate(predictor, source, indices, stage, **kwargs)


def _evaluate(predictor, source, indices: list[int] | None, out_dir: Path | None, *,
              save_predictions: bool, figures: bool, progress: bool,
              info: dict[str, Any] | None) -> dict[str, Any]:
  """`evaluate`, writing into out_dir (a staged folder) as it goes."""
  indices = list(range(len(source))) if indices is None else list(indices)
  if not indices:
    raise SljaxError("no scenes to evaluate (empty dataset or split)")
  pooled = {r: metrics.DisparityAccumulator() for r in REGIONS}
  used = {r: 0 for r in REGIONS}
  patterns = {"left": metrics.PatternAccumulator(), "right": metrics.PatternAccumulator()}
  pattern_notes: set[str] = set()
  rows = []
  for i in tqdm(indices, desc="evaluate", disable=None if progress else True):
    scene = _load(source, i)
    label = _scene_label(source, i, scene)
    where = _scene_where(source, i, label)
    if scene.im0.shape[:2] != scene.im1.shape[:2]:
      raise SljaxError(f"{where}: im0 is {scene.im0.shape[1]}x{scene.im0.shape[0]} but im1 is "
                       f"{scene.im1.shape[1]}x{scene.im1.shape[0]}; the views must have one size")
    if scene.calib is not None:  # another resolution's calib.txt gives wrong depth metrics
      check_calib_size(scene.calib, scene.im0.shape[:2], f"{where}: calib.txt")
    try:
      out = predictor(scene.im0, scene.im1, calib=scene.calib)
    except SljaxError as e:
      raise SljaxError(f"{where}: {e}") from None
    row: dict[str, Any] = {"scene": label, "has_gt": scene.disp0 is not None}
    if scene.disp0 is not None:
      for region in REGIONS:
        if region == "seg" and scene.mask0 is None:
          continue
        mask = scene.mask0 if region == "seg" else None
        acc = metrics.DisparityAccumulator()
        acc.add(out["disparity"], scene.disp0, mask, scene.calib, name=where)
        row[region] = acc.result()
        check_mae(row[region], scene.disp0, where)  # before it is pooled into the report
        pooled[region].add(out["disparity"], scene.disp0, mask, scene.calib, name=where)
        used[region] += 1
    scared_row = _scared_row(source, i, scene, out["disparity"], where)
    if scared_row is not None:
      row["scared"] = scared_row
    if "patterns" in out:
      for view, pred_key, gt in (("left", "patterns", scene.sl0),
                                 ("right", "patterns_right", scene.sl1)):
        if pred_key not in out or gt is None:
          continue
        if gt.shape != out[pred_key].shape:
          pattern_notes.add(f"pattern accuracy ({view} view) skipped: the dataset has "
                            f"{gt.shape[-1]} patterns per view, the model predicts "
                            f"{out[pred_key].shape[-1]}")
          continue
        one = metrics.PatternAccumulator()
        one.add(out[pred_key], gt)
        patterns[view].add(out[pred_key], gt)
        row[f"patterns_{view}"] = one.result()
      if figures:
        out = dict(out, uncertainty=_uncertainty(out))
    if out_dir is not None and save_predictions:
      path = out_dir / "predictions" / f"{label}.pfm"
      path.parent.mkdir(parents=True, exist_ok=True)
      write_pfm(path, out["disparity"])
    if out_dir is not None and figures:
      _figure(out_dir / "figures" / f"{label}.png", label, scene, out,
              f"{predictor.model_name} ({predictor.mode})")
    rows.append(row)

  if used["full"] and pooled["full"].n_pixels == 0:  # the scenes' truth is all unknown
    raise SljaxError(no_usable_disparity(str(getattr(source, "root", "dataset")),
                                         used["full"]))
  report: dict[str, Any] = dict(info or {})
  report.update({
      "model": predictor.model_name,
      "mode": predictor.mode,
      "resolution": predictor.describe(),
      "n_scenes": len(rows),
      "n_scenes_with_gt": sum(r["has_gt"] for r in rows),
      "pooled": {},
      "per_scene": rows,
      "notes": sorted(pattern_notes),
  })
  for region in REGIONS:
    if used[region]:
      report["pooled"][region] = dict(pooled[region].result(), n_scenes=used[region])
  for view in ("left", "right"):
    if patterns[view].known:
      report["pooled"][f"patterns_{view}"] = patterns[view].result()
  scored = [r["scared"] for r in rows if "depth_mae_mm" in r.get("scared", {})]
  if scored:
    done = [r["depth_mae_mm"] for r in scored if not r["excluded"]]
    report["pooled"]["scared"] = {
        "frame": "original (unrectified, distorted) left view",
        "keyframes": len(done), "excluded": len(scored) - len(done),
        "depth_mae_mm": float(np.mean(done)) if done else float("nan")}
  if report["n_scenes_with_gt"] == 0:
    report["notes"].insert(0, NO_GT_NOTE)
  if out_dir is not None:
    write_report(report, out_dir)
  return report


def json_safe(value: Any) -> Any:
  """NaN/inf -> None and numpy scalars -> Python numbers, so that reports are strict JSON."""
  if isinstance(value, dict):
    return {k: json_safe(v) for k, v in value.items()}
  if isinstance(value, (list, tuple)):
    return [json_safe(v) for v in value]
  if isinstance(value, (float, np.floating)):
    return float(value) if math.isfinite(value) else None
  if isinstance(value, np.integer):
    return int(value)
  if isinstance(value, np.bool_):
    return bool(value)
  return value


def _fmt(value: Any, key: str = "") -> str:
  if value is None or (isinstance(value, float) and not math.isfinite(value)):
    return "-"
  if isinstance(value, (int, np.integer)) or key.endswith("n_pixels"):
    return str(int(value))
  if key.startswith("bad") or key in ("d1", "invalid_pred", "pattern_acc"):
    return f"{value:.2f}"
  return f"{value:.3f}"


def markdown_report(report: dict[str, Any]) -> str:
  """The report as Markdown: context lines, the pooled table, pattern accuracy, per-scene rows."""
  lines = [f"# Evaluation: {report['model']}", ""]
  for key, title in (("checkpoint", "checkpoint"), ("dataset", "dataset"), ("split", "split")):
    if report.get(key) is not None:
      lines.append(f"- {title}: `{report[key]}`")
  lines.append(f"- scenes: {report['n_scenes']} ({report['n_scenes_with_gt']} with ground truth)")
  lines.append(f"- resolution mode: {report['mode']} ({report['resolution']})")
  for note in report.get("notes", []):
    lines.append(f"- note: {note}")
  lines.append("")
  pooled = report["pooled"]
  keys = [k for k in metrics.DISPARITY_KEYS]
  if any("depth_mae_mm" in pooled.get(r, {}) for r in REGIONS):
    keys += ["depth_mae_mm", "depth_iqr_mm"]
  regions = [r for r in REGIONS if r in pooled]
  if regions:
    lines.append("## Pooled over all pixels")
    lines.append("")
    rows = [[r.capitalize(), str(pooled[r]["n_scenes"])] + [_fmt(pooled[r].get(k), k) for k in keys]
            for r in regions]
    lines += tables.table(["region", "scenes"] + [_HEADERS[k] for k in keys], rows)
    lines.append("")
  for view in ("left", "right"):
    p = pooled.get(f"patterns_{view}")
    if p:
      lines.append(f"Pattern accuracy ({view} view): {_fmt(p['pattern_acc'], 'pattern_acc')} % "
                   f"over {p['pattern_n_pixels']} known pattern pixels.")
      lines.append("")
  scared = pooled.get("scared")
  if scared:
    lines.append("## SCARED (scared_toolkit rules, original frame)")
    lines.append("")
    lines.append(f"Depth MAE {_fmt(scared['depth_mae_mm'])} mm: mean over {scared['keyframes']} "
                 f"keyframe(s) in the {scared['frame']}; {scared['excluded']} excluded "
                 "(ground truth on under 10% of the pixels).")
    lines.append("")
    rows = []
    for r in report["per_scene"]:
      k = r.get("scared", {})
      if "coverage" in k:
        mae = "excluded" if k["excluded"] else _fmt(k["depth_mae_mm"])
        rows.append([r["scene"], f"{100 * k['coverage']:.1f}", f"{100 * k['assessed']:.1f}", mae])
    lines += tables.table(["keyframe", "coverage %", "assessed %", "depth MAE mm"], rows)
    lines.append("")
  if regions:
    lines.append("## Per scene")
    lines.append("")
    header = ["scene", "MAE px", "bad-2 %", "D1 %"]
    if "seg" in regions:
      header += ["Seg MAE px"]
    if "depth_mae_mm" in keys:
      header += ["depth MAE mm"]
    rows = []
    for r in report["per_scene"]:
      full = r.get("full", {})
      cells = [r["scene"], _fmt(full.get("mae")), _fmt(full.get("bad_2"), "bad_2"),
               _fmt(full.get("d1"), "d1")]
      if "seg" in regions:
        cells.append(_fmt(r.get("seg", {}).get("mae")))
      if "depth_mae_mm" in keys:
        cells.append(_fmt(full.get("depth_mae_mm")))
      rows.append(cells)
    lines += tables.table(header, rows)
    lines.append("")
  return "\n".join(lines)


def csv_rows(report: dict[str, Any]) -> tuple[list[str], list[dict[str, Any]]]:
  """(columns, rows) of the per-scene table: region_metric columns plus pattern accuracy."""
  columns = ["scene", "has_gt"]
  flat_rows = []
  for r in report["per_scene"]:
    flat: dict[str, Any] = {"scene": r["scene"], "has_gt": int(r["has_gt"])}
    for key, value in r.items():
      if isinstance(value, dict):
        for k, v in value.items():
          flat[f"{key}_{k}"] = v
    flat_rows.append(flat)
    for k in flat:
      if k not in columns:
        columns.append(k)
  return columns, flat_rows


def write_report(report: dict[str, Any], out_dir: str | os.PathLike) -> None:
  """Writes metrics.json, metrics.md and per_scene.csv into out_dir."""
  out_dir = Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  # Each file whole or not at all: --overwrite onto a full disk keeps the earlier one.
  files.write_text(out_dir / "metrics.json",
                   json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n")
  files.write_text(out_dir / "metrics.md", markdown_report(report))
  columns, rows = csv_rows(report)
  text = io.StringIO()
  w = csv.DictWriter(text, fieldnames=columns, restval="")
  w.writeheader()
  for row in rows:
    w.writerow({k: ("" if v is None or (isinstance(v, float) and not math.isfinite(v)) else v)
                for k, v in row.items()})
  files.write_text(out_dir / "per_scene.csv", text.getvalue())
