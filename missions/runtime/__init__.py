"""What every ``fimnav`` command's process shares: how a signal stops it (``signals``) and the
one place that makes a results directory (``rundir``). Imports no other part of ``missions``."""
