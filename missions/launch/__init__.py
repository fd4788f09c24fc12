"""A swarm flown as processes on this machine (``fimnav launch``): the launcher and what it
composes (``supervisor``, ``forkspawn``, ``clock``, ``collect``, ``accounting``, ``commands``,
``view``, ``view_peb``, ``gcs``), and the live view's server (``liveview``). It starts commands
by the program's name, never by importing :mod:`missions.cli`."""
