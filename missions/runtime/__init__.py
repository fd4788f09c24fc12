"""What every ``fimnav`` command's process shares: how a signal stops it (``signals``), the
one place that makes a results directory (``rundir``) and the numerical libraries' thread
pools (``threads``). Imports no other part of ``missions``."""
