"""The benchmark records of every CPU measured, as one Markdown table (docs/benchmarks.md).

Every benchmark appends its rows, with the machine, to `benchmarks/results/<cpu>.jsonl`
(`common.record`). This prints, per CPU kind, the latest record of each headline figure:

  python benchmarks/records.py            # all CPUs
  python benchmarks/records.py --all      # every record, not only the latest per figure
"""

import argparse
import json
from pathlib import Path

from common import RESULTS, cpu_description


def load(folder: Path) -> dict[str, list[dict]]:
  """Records per CPU key (file stem), oldest first."""
  out = {}
  for path in sorted(folder.glob("*.jsonl")):
    with open(path, encoding="utf-8") as f:
      out[path.stem] = [json.loads(line) for line in f if line.strip()]
  return out


def headlines(entry: dict) -> list[tuple[str, str]]:
  """(figure, value) pairs of one record: the numbers a reader compares across CPUs."""
  b, rows, out = entry["benchmark"], entry["rows"], []
  for r in rows:
    if b == "bench_nets" and r.get("table") == "models":
      what = f"{r['model']} {r['mode']}, {r['size']}px b{r['batch']}, vs {r['torch_side']}"
      out.append((what, f"{r['ratio']:.2f}x ({r['sljax_s']:.2f} s vs {r['torch_s']:.2f} s)"))
    elif b == "bench_train":
      precision = "" if entry.get("precision", "fp32") == "fp32" else f" {entry['precision']}"
      flags = f" [{entry['xla_flags']}]" if entry.get("xla_flags") else ""
      out.append((f"train loop {entry.get('preset')} {entry.get('net')}{precision}{flags}: "
                  f"{r['what']}",
                  f"{r['samples_per_s']:.2f} samples/s ({r['ratio_to_a']:.3f}x step)"))
    elif b == "bench_corr":
      out.append((f"correlation {r['width']}x{r['height']} t={r['t']} u={r['u']}",
                  f"{r['rows_s']:.3f} s ({r['shifts_s'] / r['rows_s']:.1f}x faster than shifts)"))
    elif b == "bench_fullres":
      what = f"pad mode {r['model']} {r['width']}x{r['height']} maxdisp {r['maxdisp']}"
      if r.get("failed"):
        out.append((what, "failed (out of memory?)"))
        continue
      mem = "peak_device_gib" if r.get("peak_device_gib") is not None else "peak_rss_gib"
      ref = ""
      if r.get("reference_s"):
        ref_mem = r.get(f"reference_{mem}") or r.get("reference_peak_rss_gib")
        ref = (f"; reference {r['reference_s']:.2f} s, {ref_mem:.1f} GiB: "
               f"{r['later_call_s'] / r['reference_s']:.2f}x")
      out.append((what, f"{r['later_call_s']:.2f} s, {r[mem]:.1f} GiB"
                  f"{' (device)' if mem == 'peak_device_gib' else ''}{ref}"))
    elif b == "bench_synthetic":
      out.append((f"renderer {entry.get('size')}px {r['path']}", f"{r['cpu_ms_per_scene']:.0f} ms CPU"))
    elif b == "bench_gpu" and r.get("table") == "agreement":
      out.append((f"{r['model']} forward vs CPU, {r['size']}px, {r['precision']} precision",
                  f"max {r['max_px']:.2g} px, mean {r['mean_px']:.2g} px, "
                  f"{r['over_1e-3_pct']:.2f}% of pixels over 1e-3 px"))
    elif b == "bench_gpu" and r.get("table") == "models":
      ms = lambda k: f"{r[k] * 1e3:.1f} ms" if r.get(k) else "-"
      torch = (f"; torch ({r.get('torch_side')}) fp32 {ms('torch_fp32_s')}, TF32 "
               f"{ms('torch_tf32_s')}" if r.get("torch_fp32_s") else "")
      out.append((f"{r['model']} {r['mode']}, {r['size']}px b{r['batch']} (ms a call)",
                  f"default {ms('sljax_default_s')}, highest {ms('sljax_highest_s')}{torch}"))
    elif b == "bench_gpu" and r.get("table") == "step" and not r.get("failed"):
      who = "reference" if r["side"] == "reference" else f"sljax {r['net']} {r.get('impl')}"
      run = ", second run (warm cache)" if r.get("run") == "second" else ""
      ratio = f" ({r['ratio']:.2f}x reference)" if r.get("ratio") else ""
      out.append((f"training step {who}, {r['width']}x{r['height']} maxdisp {r['maxdisp']} b"
                  f"{r['batch']} {r['precision']}{run}",
                  f"{r['step_s'] * 1e3:.0f} ms{ratio}, first step {r['first_step_s']:.0f} s, "
                  f"peak {r['peak_gib']:.1f} GiB"))
    elif b == "bench_convT":
      size = f"{'x'.join(map(str, r['x'][1:4]))}x{r['x'][4]} b{r['x'][0]}"
      value = ", ".join(f"{p} {r[f'{p}_ms']:.2f} ms" for p in ("fwd", "dx", "dk", "both")
                        if f"{p}_ms" in r)
      lax = f" ({r['both_over_lax']:.2f}x lax)" if "both_over_lax" in r else ""
      out.append((f"transposed conv {r['layer']} {size} {r['form']} {r['dtype']}", value + lax))
    elif b == "main_job":
      out.append((r["what"], r["value"]))
  return out


def table(records: dict[str, list[dict]], every: bool = False) -> str:
  """The Markdown table: one section per CPU, the latest value of each figure (or all)."""
  lines = []
  for key, entries in records.items():
    if not entries:
      continue
    where = (entries[-1]["machine"] if entries[-1].get("backend", "cpu") != "cpu"
             else cpu_description(entries[-1]["cpu"]))  # an accelerator's file: the whole machine
    lines += [f"\n**{where}** (`{key}`)\n",
              "| figure | value | when | commit | load | source |", "| --- | --- | --- | --- | --- | --- |"]
    latest: dict[str, tuple[str, dict]] = {}
    for e in entries:
      for what, value in headlines(e):
        if every:
          lines.append(row(what, value, e))
        else:
          latest[what] = (value, e)
    lines += [row(what, value, e) for what, (value, e) in latest.items()]
  return "\n".join(lines)


def row(what: str, value: str, e: dict) -> str:
  """One table row with where the number came from."""
  return (f"| {what} | {value} | {e['time'][:10]} | {e.get('commit', '?')} | "
          f"{e.get('loadavg_1min') if e.get('loadavg_1min') is not None else '?'} | {e.get('source', 'measured')} |")


def main() -> None:
  """Prints the table."""
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--all", action="store_true", help="every record, not the latest per figure")
  ap.add_argument("--folder", type=Path, default=RESULTS)
  args = ap.parse_args()
  print(table(load(args.folder), args.all))


if __name__ == "__main__":
  main()
