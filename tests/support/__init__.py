"""What the tests share: real subprocesses (:mod:`.proc`) and ``fimnav launch`` runs (:mod:`.launch`)."""
