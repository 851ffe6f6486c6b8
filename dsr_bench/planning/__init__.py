"""The planning track (issue 17; paper Sec. 3.1 "Applying DSR in Robot Manipulation", Sec. 4.3 and the
appendix "Action Sampling for MPC"): push the objects of a start scene to a target state in 3 pushes,
with shooting-based MPC over a model's predicted next states. docs/planning.md has the protocol.

Modules (numpy, h5py and torch only: no simulator; the simulator side is `generators.planning`):

  protocol   the track's constants, the observation handed to a planner, the `Planner` protocol
  tasks      the task file format (writer, validated reader), task digests, task sets and their manifest
  sampling   candidate actions: around predicted masks (the appendix) or uniform over valid actions
  cost       the paper's cost: sum over objects of lambda * position MSE - IoU, Hungarian matching
  planners   random (lower bound), oracle (true next states from a simulator callback), learned models
  learned    a batch of candidate actions through a DSR-Net-like model against one state
  runner     the MPC loop over an `Environment` (observe, sample, score, execute), one plan per task
  plans      the plan file (every observation, candidate set, cost and chosen action)
  results    final-vs-target voxel IoU per task, the results JSON (its leaderboard rows: dsr_bench.leaderboard.board)
  verify     nothing trusted: tasks against the pin, plans against their tasks, results recomputed and checked
"""
