"""The in-process study of a mission: the vectorised simulator (``simulator``), and a results
directory with what it holds: CSV, summary and the paper's figures (``results``, ``rundir``,
``figures``, ``exports``). Never imports :mod:`missions.launch` nor :mod:`missions.cli`."""
