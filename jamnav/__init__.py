"""The ``jamnav`` command line and the supervisor of the distributed system.

- ``cli``: the parser of every sub-command and ``main``; the commands by group in
  ``cli_radio`` (scenario show, sinr, map), ``cli_experiments`` (eval, table, figures,
  online-map, cloud-latency), ``cli_training`` (train, fit-sinr), ``cli_up`` (up, chaos) and
  ``cli_runtime`` (console, record, replay, jammer, status, router).
- ``arguments``: the options several commands share and the checks of their values.
- ``supervisor``: ``jamnav up``'s processes, started, followed, restarted and stopped;
  ``routers``: its one or two routers; ``run_report``: the report, summary and figures after
  the run; ``chaos``: the same system under faults, and the ledger of what came through.
- ``recording``: runs kept as MCAP files (record, replay); ``event_lines``: a run's events as
  lines for people; ``progress``: the progress bar of long commands; ``console``: the
  operator's console in a browser; ``__main__``: the ``jamnav`` entry point, which sizes
  BLAS to one thread before numpy loads.
"""

