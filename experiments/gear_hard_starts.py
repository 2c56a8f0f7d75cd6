"""The training starts of given iterations of a params-exploration run, replayed by its final
deterministic controller: are an iteration's failures its starts' or its exploration's?

python experiments/gear_hard_starts.py RUN_DIR ITERATION [ITERATION ...]
"""

import json
import sys
from pathlib import Path

from learner_node.config import TrainConfig
from learner_node.trainer import CHECKPOINT, Trainer, make_evaluator

run = Path(sys.argv[1])
wanted = {int(a) for a in sys.argv[2:]}
cfg = TrainConfig.from_sources(None, TrainConfig.with_defaults(json.loads((run / "config.json").read_text())))
fresh = Trainer(cfg)  # the same generator: episode_plan draws the same starts whatever the policy
starts = {}
for it in range(1, max(wanted) + 1):
    plan = fresh.episode_plan()
    if it in wanted:
        starts[it] = sorted({s for s, _, _ in plan})
trained = Trainer(cfg)
trained.load_checkpoint(run / CHECKPOINT)
ev = make_evaluator(trained.policy)
history = json.loads((run / "metrics.json").read_text())
for it, seeds in starts.items():
    ok = [trained.runner.run_episode(ev, None, s, None).final_success for s in seeds]
    print(f"iteration {it}: training success {history[it - 1]['success_rate']:.2f}; final deterministic "
          f"controller on its {len(seeds)} distinct starts: {sum(ok)}/{len(seeds)}")
