"""The in-process study of a mission: a study as a library call (``montecarlo``: ``run_study``)
whose chunks of trials run on an executor (``executors``), the vectorised simulator
(``simulator``) and what a run is and gives (``records``, without the simulator's kernels), the optimum (``optimum``), and a results directory with what it holds: CSV,
summary and the paper's figures (``results``, ``layout``, ``figures``, ``exports``). Never
imports :mod:`missions.launch` nor :mod:`missions.cli`."""
