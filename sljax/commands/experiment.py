"""`sljax experiment run PLAN OUT` / `report OUT` / `status OUT`: the paper's experiments."""

import argparse
import signal
from pathlib import Path

from sljax.experiment.budget import calibrate as cal, regime as reg
from sljax.experiment.design import plans
from sljax.experiment.report import build as rep
from sljax.experiment.running import price, runner, status as st, submit as subm, workers


def register(subparsers) -> None:
  """Adds the `experiment` subcommand and its run / report / status / calibrate / regime / plans
  actions."""
  p = subparsers.add_parser(
      "experiment",
      description="Runs a plan (a grid of training runs: model and strategy, training fraction, "
                  "seed, domain, fine-tuning, evaluation sets) under OUT, then reports every "
                  "cell with means and 95% intervals over seeds and paired comparisons. "
                  "Interrupt it at any time: the same command continues where it stopped.")
  sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
  r = sub.add_parser("run", help="train and score every unfinished cell of a plan",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  r.add_argument("plan", metavar="PLAN",
                 help=f"one of {', '.join(plans.PLANS)} (`sljax experiment plans` says what "
                      "each one is)")
  r.add_argument("out", metavar="OUT", help="experiment folder (shared by plans that share cells)")
  r.add_argument("--scale", default="cpu",
                 help="smoke (minutes, for tests), cpu (a 2-core CPU, 64x64), cpu128 (128x128) or "
                      "paper (an accelerator)")
  r.add_argument("--seeds", type=int, default=None,
                 help="seeds 0..N-1 (more can be added later); default 1 at the smoke scale, "
                      "3 otherwise")
  r.add_argument("--data", default=None,
                 help="your scene-format folder: replaces synthetic objects (table2, table3) or "
                      "synthetic tissue as the fine-tuning target (table1, fig7)")
  r.add_argument("--eval-data", action="append", default=[], metavar="DIR",
                 help="table3: also score on this scene-format folder (Middlebury, imported "
                      "SCARED); repeatable")
  r.add_argument("--no-progress", action="store_true", help="no progress bar")
  r.add_argument("--lease", type=float, default=workers.LEASE_S, metavar="SECONDS",
                 help="a worker on another host whose heartbeat is this old counts as gone and "
                      "its cell is taken over (every worker of a grid may run on its own host: "
                      "start as many as you like on one OUT)")
  r.add_argument("--log-path", default=None, help=argparse.SUPPRESS)  # set by submit's jobs
  _dry_run_options(r)
  r.add_argument("--workers", type=int, default=1,
                 help="--dry-run: the wall time on this many workers")
  r.set_defaults(func=run_plan)
  _submit_parser(sub)
  rep = sub.add_parser("report", help="write OUT/report.md, report.json and figures",
                       description="Reports every plan run under OUT (cells not finished yet "
                                   "are listed as missing).")
  rep.add_argument("out", metavar="OUT", help="experiment folder")
  rep.add_argument("--plans", default=None, metavar="NAMES",
                   help="only these plans of those run under OUT, comma-separated "
                        "(e.g. table2-v2 while fig7-v2 runs in the same folder)")
  rep.set_defaults(func=report)
  s = sub.add_parser("status", help="finished, training and waiting cells, times, time left",
                     description="Where the plans run under OUT stand (safe beside a running "
                                 "grid): cells finished, trained but not scored, training "
                                 "(with their epoch) and waiting; minutes a cell by arm; the "
                                 "CPUs they ran on; training time left, estimated from "
                                 "finished cells of the same arm.")
  s.add_argument("out", metavar="OUT", help="experiment folder")
  s.add_argument("--seeds", type=int, default=None,
                 help="the grid's target seed count (default: the seeds run so far)")
  s.set_defaults(func=status)
  c = sub.add_parser(
      "calibrate", help="set a v2 plan's budgets: long runs on validation, the plateau rule",
      description="Trains each arm and phase of a v2 plan once (seed 0, fixed learning rate, "
                  "the scale's long calibration budget, validated on every validation scene) "
                  "under OUT, resumably, applies the pre-registered plateau rule "
                  "(sljax.experiment.budget.calibrate) and prints the budgets to commit into the "
                  "scale; OUT/calibration-PLAN.json keeps the curves.",
      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  c.add_argument("plan", metavar="PLAN", help=f"{', '.join(plans.CALIBRATED)}")
  c.add_argument("out", metavar="OUT", help="calibration folder (`experiment run` calibrates "
                                            "in the grid's own OUT where budgets are missing)")
  c.add_argument("--scale", default="cpu128", help="smoke, cpu or cpu128")
  c.add_argument("--no-progress", action="store_true", help="no progress bar")
  c.set_defaults(func=calibrate)
  g = sub.add_parser(
      "regime", help="v3, v4: where stl overfits, from the pilot's curves (docs/plan-v3.md, "
      "docs/plan-v4.md)",
      description="Applies the pre-registered regime rule (sljax.experiment.budget.regime) to the "
                  "v3-pilot cells under OUT: the largest training fraction whose smoothed mean "
                  "validation curve ends at least 10% above its minimum, and the budget (twice "
                  "the minimum's epoch); for a v4-pilot folder the same rule on steps, per "
                  "setting, and the v4 grid's seed count by the plan's 24-hour rule "
                  "(docs/plan-v4.md). Writes OUT/regime.json, regime.md and a figure.",
      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  g.add_argument("out", metavar="OUT", help="the pilot's experiment folder")
  g.add_argument("--scale", default="cpu", help="the pilot's scale (cpu; smoke for tests)")
  g.add_argument("--seeds", type=int, default=2, help="the pilot's seed count")
  g.set_defaults(func=regime)
  ls = sub.add_parser("plans", help="list the plans and scales")
  ls.set_defaults(func=list_plans)


def _dry_run_options(parser) -> None:
  """--dry-run and --gpu, shared by run and submit."""
  parser.add_argument("--dry-run", action="store_true",
                      help="print the cells, what each waits for, their steps, the GPU-hours "
                           "and the wall time on --workers workers; train, submit and write "
                           "nothing")
  parser.add_argument("--gpu", choices=("h100", "h200"), default=None,
                      help="--dry-run: price with this GPU's measured step times (default: "
                           "this machine's, from cells finished under OUT)")


def _seeds(args: argparse.Namespace) -> int:
  return args.seeds if args.seeds is not None else 1 if args.scale == "smoke" else 3


def dry_run(args: argparse.Namespace) -> int:
  """Prints what the plan would cost; writes nothing."""
  plan, calibrating = price.plan_to_price(args.plan, args.scale, _seeds(args), args.data,
                                          tuple(args.eval_data))
  print(price.dry_run(plan, args.out, args.workers, args.gpu, calibrating))
  return 0


def run_plan(args: argparse.Namespace) -> int:
  """Runs the plan and says how to report it."""
  if args.dry_run:
    return dry_run(args)
  plan, then = cal.worker_plan(args.plan, args.scale, _seeds(args), args.data,
                               tuple(args.eval_data), args.out)
  res = runner.run(plan, args.out, progress=not args.no_progress, lease=args.lease,
                   log_path=args.log_path, then=then)
  left_out = (f"; {len(res['diverged'])} cell(s) left out as diverged (each diverged.json "
              "says why)" if res["diverged"] else "")
  done = (f"{args.plan}: trained {res['trained']} cell(s), scored {res['evaluated']} set(s) in "
          f"{res['seconds'] / 60:.1f} min{left_out}")
  if res["stopped"]:
    print(f"{done}; stopped by {res['stopped']}: run the same command to go on")
    return 128 + int(getattr(signal, res["stopped"]))
  if res["left"]:
    print(f"{done}; nothing left for this worker: " + "; ".join(
        f"{cell} {who}" for cell, who in res["left"].items())
          + f". Follow with: sljax experiment status {args.out}")
    return 0
  print(f"{done}; report with: sljax experiment report {args.out}")
  return 0


def _submit_parser(sub) -> None:
  """The `submit` action's options."""
  b = sub.add_parser(
      "submit", help="N `run` workers on one OUT through submitit: a SLURM job array, or local",
      description="Submits N workers of `sljax experiment run PLAN OUT` (the [cluster] extra: "
                  "submitit): a SLURM job array (preempted or timed-out jobs checkpoint their "
                  "cell and are requeued), or with --local N processes on this machine, one "
                  "GPU each where it has several. The workers divide the cells; follow with "
                  "`sljax experiment status OUT`, report with `sljax experiment report OUT` "
                  "once every cell is done.",
      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  b.add_argument("plan", metavar="PLAN", help="a plan, as for `run`")
  b.add_argument("out", metavar="OUT", help="experiment folder, on a file system every node "
                                            "sees")
  b.add_argument("--workers", type=int, required=True, help="how many workers (jobs)")
  b.add_argument("--local", action="store_true", help="run the workers on this machine")
  b.add_argument("--scale", default="cpu", help="as for `run`")
  b.add_argument("--seeds", type=int, default=None, help="as for `run`")
  b.add_argument("--data", default=None, help="as for `run`")
  b.add_argument("--eval-data", action="append", default=[], metavar="DIR", help="as for `run`")
  b.add_argument("--partition", default=None, help="SLURM partition")
  b.add_argument("--gpus-per-worker", type=int, default=None,
                 help="GPUs per worker (default 1; --local: 1 where the machine has GPUs)")
  b.add_argument("--cpus-per-worker", type=int, default=None, help="CPUs per worker")
  b.add_argument("--time", default="24:00:00",
                 help="time limit of each job (sbatch's formats); a worker still training then "
                      "is checkpointed and requeued")
  b.add_argument("--account", default=None, help="SLURM account")
  b.add_argument("--sbatch", action="append", default=[], metavar="NAME=VALUE",
                 help="another sbatch option, e.g. qos=preemptible, constraint=h100; "
                      "repeatable")
  b.add_argument("--setup", action="append", default=[], metavar="LINE",
                 help="a shell line each job runs first, e.g. 'module load cuda'; repeatable")
  b.add_argument("--lease", type=float, default=workers.LEASE_S, metavar="SECONDS",
                 help="as for `run`")
  b.add_argument("--wait", action="store_true", help="wait for every worker to end")
  _dry_run_options(b)
  b.set_defaults(func=submit_workers)


def submit_workers(args: argparse.Namespace) -> int:
  """Checks the options and the plan, records it under OUT and submits the workers."""
  if args.dry_run:
    return dry_run(args)
  res = subm.Resources(args.workers, args.partition, args.gpus_per_worker, args.cpus_per_worker,
                       subm.parse_minutes(args.time), args.account, subm.parse_sbatch(args.sbatch),
                       tuple(args.setup))
  # A plan calibrated in OUT registers its calibration cells first; the workers go on to it.
  first, then = cal.worker_plan(args.plan, args.scale, _seeds(args), args.data,
                                tuple(args.eval_data), args.out)
  grid = None if then is None else plans.provisional_plan(args.plan, args.scale, _seeds(args),
                                                          args.data, tuple(args.eval_data))
  from sljax import cli  # pylint: disable=import-outside-toplevel  (cli imports this module)
  subm.submit_grid(first, Path(args.out), res, local=args.local, wait=args.wait,
                   lease=args.lease, entry=cli.main, log=lambda line: print(line, flush=True),
                   grid=grid)
  return 0


def calibrate(args: argparse.Namespace) -> int:
  """Runs the calibration and prints the budgets by the plateau rule."""
  result = cal.calibrate(args.plan, args.scale, args.out, progress=not args.no_progress)
  print(f"budgets for scale {args.scale} by the plateau rule (commit them into "
        "sljax/experiment/design/scales.py, SCALES[...].budgets, or let `experiment run` "
        "use them in the grid's own OUT):")
  for line in cal.budget_lines(result):
    print("  " + line)
  if result["missing"]:
    print(f"not finished: {', '.join(result['missing'])}")
  return 0


def report(args: argparse.Namespace) -> int:
  """Writes the report and prints where."""
  path = rep.write_report(args.out, args.plans.split(",") if args.plans else None)
  print(f"wrote {path} (+ report.json, figures/)")
  return 0


def regime(args: argparse.Namespace) -> int:
  """Applies the regime rule to the pilot and prints the outcome."""
  result = reg.write(args.out, args.scale, args.seeds)
  print("\n".join((reg.markdown_v4 if "settings" in result else reg.markdown)(result)).rstrip())
  print(f"wrote {args.out}/regime.json, regime.md")
  return 0


def status(args: argparse.Namespace) -> int:
  """Prints where the grid stands."""
  print(st.grid_status(args.out, args.seeds))
  return 0


def list_plans(args: argparse.Namespace) -> int:
  """Prints the plans and scales."""
  del args
  print(plans.__doc__.split("Plans:")[1].strip())
  for scale in plans.SCALES.values():
    print(f"scale {scale.name}: {scale.size}x{scale.size}, t = {scale.t}, maxdisp "
          f"{scale.maxdisp}, {scale.objects_n} objects scenes, batch {scale.batch_size}, Adam "
          f"{scale.lr:g}, epochs {scale.schedule.epochs} (1/16: {scale.schedule.small_epochs}), "
          f"fine-tuning {scale.schedule.finetune_epochs} epochs on {scale.tissue_n} tissue "
          f"scenes; {scale.note}"
          + (f"; v2: test sets of {scale.v2.test_n} scenes per domain, windows "
             f"{', '.join(map(str, scale.v2.windows)) or 'none set'}, budgets "
             + (", ".join(f"{a} {p}: {e}" for (a, p), e in scale.v2.budgets)
                or "not committed (a grid's OUT calibrates them first)")
             if scale.v2.test_n else "")
          + (f"; v3: pilot at {', '.join(scale.v3.fractions)}, {scale.v3.pilot_epochs} epochs"
             if scale.v3 else ""))
  return 0
