"""Choose Chae runs' checkpoints again, on a larger draw at the bar's hardest corner, without retraining.

    python -m experiments.chae_reselect runs/NAME --seeds 0 1 2 --out runs/NAME_reselected \
        [--shortlist 4] [--draw 98] [--trials 500]

Training's own selection (``agent.chae.select``) scores every validated checkpoint on 200 trials per TTC and keeps the
one inside both bars with the fewest needless stops. At 200 trials a bump is 0.5 %, so checkpoints whose true rate
at TTC 1.5 s is anywhere from 0 to 2 % pass alike, and ensembles of such members miss the 1 % bar on fresh draws
(docs/results/chae/notes/checkpoint_selection_and_rescoring.md). For runs trained with ``agent.chae.select.keep=true``
this applies ``agent.chae.select.rescore``'s rule afterwards (``chae.system.rescore_kept``):

1. the candidates are the kept checkpoints inside both bars on training's selection draw (if none, the run keeps
   its ``best.pt``);
2. the ``--shortlist`` of them bumping least at TTC 1.5 s there (then fewer stops, then later) drive another
   selection draw (``--draw``, never an evaluation or a judging draw): ``--trials`` Scenario-1 trials at TTC 1.5 s
   and as many in Scenario 2;
3. the chosen one has the most room under both bars: the smallest max(bumps / 1 %, needless stops / 5 %), the later
   on a tie.

``--out`` receives a copy of each run with the chosen checkpoint as its ``best.pt`` and the scores in
``reselection.json``, so that ``experiments.chae_margin`` and ``worldmodel.evaluate evaluate.family=chae`` read it as
they read any experiment.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

from worldmodel.banks import validation_draw
from worldmodel.checkpoints import read_checkpoint


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="runs/NAME, holding agent_chae_dqn_chae/seedK with validated/")
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--out", type=Path, required=True, help="a new runs/NAME2 for the rechosen runs")
    parser.add_argument("--shortlist", type=int, default=4)
    parser.add_argument(
        "--draw", type=validation_draw, default=98, help="bank seed: not 99 (training's), 102/103, 2017"
    )
    parser.add_argument("--trials", type=int, default=500, help="per TTC and in Scenario 2")
    parser.add_argument("--ttcs", type=float, nargs="+", default=[1.5], help="the TTCs rescored, s")
    args = parser.parse_args(argv)
    if args.draw in (99, 102, 103, 2017):
        raise SystemExit(f"--draw {args.draw} is training's selection draw or a judging draw; choose another seed")

    import torch

    from worldmodel import artifacts
    from worldmodel.config import compose
    from worldmodel.families.chae import system as chae

    torch.set_num_threads(1)
    run, out = args.run.resolve(), args.out.resolve()
    cfg = compose("evaluate", [f"experiment={run.name}", f"paths.runs={run}", "evaluate.family=chae"])
    agents = {a.seed: a for a in artifacts.trained_agents(cfg, family="chae") if a.variant == "dqn_chae"}
    missing = [s for s in args.seeds if s not in agents]
    if missing:
        raise SystemExit(f"{run} has no dqn_chae runs for seeds {missing}; it has {sorted(agents)}")
    sel = SimpleNamespace(
        ttcs=[1.5],
        max_bump=chae.BAR_BUMP,
        max_stops=chae.BAR_STOPS,
        rescore=args.shortlist,
        rescore_seed=args.draw,
        rescore_trials=args.trials,
        rescore_ttcs=args.ttcs,
    )
    print(f"draw {args.draw}, {args.trials} trials at each TTC of {args.ttcs} s and in Scenario 2\n")
    print("| seed | training's choice | rescored (episode: highest bumps % / stops %) | chosen |\n|---:|---|---|---|")
    for seed in args.seeds:
        agent = agents[seed]
        src = agent.dir(cfg)
        last = read_checkpoint(src / "last.pt")
        trained = chae.selected(last["curve"]["validation"], chae.BAR_BUMP)
        record = chae.rescore_kept(cfg, agent, src, last["curve"]["validation"], sel)
        chosen = record["chosen"]
        dst = out / src.relative_to(run)
        dst.mkdir(parents=True, exist_ok=True)
        for name in ("last.pt", "metrics.json", "provenance.json"):
            shutil.copy2(src / name, dst / name)
        shutil.copy2(chae.validated_path(src, chosen["episode"]) if chosen else src / "best.pt", dst / "best.pt")
        # the copy is a run of its own: its record names the checkpoints it now holds
        artifacts.write_provenance(dst, {**artifacts.read_provenance(dst), "outputs": artifacts.output_digests(dst)})
        (dst / "reselection.json").write_text(json.dumps({**record, "training_choice": trained}, indent=1))
        listed = ", ".join(
            f"{r['episode']}: {r['bump_rate']:.1f} / {r['unnecessary_stop_rate']:.1f}" for r in record["rescored"]
        )
        print(
            f"| {seed} | {trained['episode']} | {listed or 'none inside both bars'} | "
            f"{chosen['episode'] if chosen else 'best.pt (kept)'} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
