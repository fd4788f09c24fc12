"""What the tests share: free ports (:mod:`.net`), waits with deadlines (:mod:`.wait`), real
subprocesses (:mod:`.proc`), ``fimnav launch`` runs (:mod:`.launch`) and Zenoh sessions and
routers (:mod:`.zenoh`)."""
