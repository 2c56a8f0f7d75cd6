#!/bin/bash
# sequential driver for docs/results/table_flow (one run at a time)
cd /work/main && source env.sh
PRIOR="--set stiffness_axial=none --set flow_init=identity"
R="nice -n 10 python -m learner_node.analysis.report --tasks peg --seeds 0,1,2 --iterations 30"
for s in 1 1.5 2 3; do
  g=$(python -c "print(f'{0.5*$s:g}')"); f=$(python -c "print(f'{0.05*$s:g}')")
  echo "=== A sigma $s ($g, $f) $(date -u)"
  $R --policies nf --sigmas $s $PRIOR --set gains=learned --set exploration=params \
    --set param_sigma_gains=$g --set param_sigma_flow=$f --set flow_input_scale=0.05 --set param_flow=subspace \
    --set param_flow_dim=8 --set param_ratio=group --set param_lr=0.1 --set param_step=current \
    --set param_adv_scale=running --set param_sigma_lr=0.01 --set param_sigma_decay=0.97 \
    --runs runs/table_flow/A --out /tmp/table_flow_out/A
done
echo "=== C $(date -u)"
$R --policies mlp --sigmas 1,1.5,2,3 --runs runs/table_flow/C --out /tmp/table_flow_out/C
for s in 1 1.5 2 3; do
  echo "=== B sigma $s $(date -u)"
  $R --policies nf --sigmas $s $PRIOR --set gains=learned --set exploration=action \
    --runs runs/table_flow/B --out /tmp/table_flow_out/B
done
echo "=== DONE $(date -u)"
