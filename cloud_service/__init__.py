"""The cloud of the paper: the online SINR map it keeps for the UAVs, and the offline training
and evaluation of the value network they fly with.

The online service (``python -m cloud_service.process``, started by ``jamnav up``):

- ``process``: the cloud process on the bus: takes the uploads, serves the latest weights of
  both networks and publishes every new version.
- ``rounds``: the cloud on the world's lockstep clock, each world step's uploads as one round.
- ``sinr_memory``: the replay memory D_w of the measurements, in SQLite.
- ``sinr_mapping``: the online SINR mapper tying the next ones together: watches the map's
  accuracy, detects a jammer change, retrains and publishes. ``change_detection``: the rule
  that declares a change; ``change_handling``: when the mapper estimates, refits and settles
  on one (``RetrainConfig``); ``map_refit``: the map network refitted on the uploads plus a
  prior over the area; ``jammer_withdrawal``: whether the jammer behind a corrected map is
  still there; ``report_models``: how probable the cloud's models make each report;
  ``mapper_outputs``: what the mapper gives out (each map it publishes).
- ``sinr_reference``: what UAVs measured with no jammer, the reference for dB reports.
- ``jammer_estimation``: the jammers' count, positions and powers from the uploads alone,
  or a provisional map's hypotheses, built on ``jammer_evidence`` (the uploads' log-likelihood
  ratio for a hypothesis), ``report_likelihood`` (how probable a level or dB report is at a
  believed SINR), ``no_jammer_belief`` (what the cloud believes of the no-jammer SINR at a
  point), ``upload_positions`` (where an upload was taken, from its features) and
  ``estimated_jammer`` (the jammer as the cloud knows it).
- ``map_correction``: the no-jammer map corrected with the estimated jammers.
- ``jammer_tracking``: a moving jammer followed through the estimates of successive windows
  of uploads (a constant-velocity Kalman filter), offline and by the mapper as uploads come;
  ``driving_jammer``: a jammer at a steady velocity fitted to many seconds of uploads at once
  (offline: the mapper does not run it).
- ``scenario_tables`` (offline): the online, perfect and outdated maps under a scenario's own
  jammers, over seeds (``jamnav jammers-table``).
- ``sinr_training``: fitting a SINR-mapping network (torch, loaded on first use; ``jamnav
  fit-sinr`` fits the survey maps with it too).

The offline parts:

- ``value_training``: Algorithm 1, the value network's training (``jamnav train``), with
  ``training_config`` (its settings), ``value_learner`` (the networks, replay memory D and
  regressions), ``training_flight`` (the episodes flown, as the learner sees them) and
  ``training_checkpoint`` (resumable runs, durable writes).
- ``evaluation``: Table I's methods flown in-process (``jamnav eval``, ``jamnav table``,
  ``jamnav figures``).
- ``ablation``: the paper's method retrained with one open choice changed at a time.
- ``latency_sweep``: missions on the online map against the cloud's latency (``jamnav
  cloud-latency``).
- ``online_map_sim``: simulated uploads through the online mapper, the paper's Fig. 2b
  (``jamnav online-map``).

Shared by both: ``torch_networks`` (the two networks as torch modules, the form both are
trained in), ``rollout`` (the vectorized world flown by a controller, and the true and
outdated maps as rasters, which ``process`` serves for comparison too) and
``simulated_measurements`` (reports as a UAV's receiver makes them).

Why the offline parts live here and not in a package of their own: in the paper the cloud is
where the value network is trained, offline on a simulator (Algorithm 1), before it is served
to the UAVs; and evaluation and the ablation fly the in-process world (``world_sim``, which the
layering lets the cloud import and not the agents: ``tests/test_layering.py``), the proposed
method on the online map the cloud runs in service, through the same ``OnlineSinrMapper``.
Apart, they would copy that code or reach into the cloud from outside it.
"""
