"""The numpy planning step of commit 48f7e03, before the compiled core: the TEST-ONLY reference of
:func:`planner.agent.plan` (``tests/simulator/test_open_loop_vs_numpy.py`` runs both on the same
inputs and compares them step by step). Never imported by production code.

Vendored verbatim from ``git show 48f7e03:planner/<module>.py`` (the modules ``plan`` needs:
``agent``, ``control``, ``fim``, ``geometry``); the only edits: ``planner.<module>`` ->
``tests.reference_numpy.planner.<module>`` in the imports of these four (sorted again;
docstrings still name the original modules). They use the production :mod:`planner.params`,
:mod:`planner.config` (``PlannerConfig``, unchanged since 48f7e03), :mod:`planner.estimator`
(types only) and :mod:`planner.sensing`, whose batched terms are unchanged since 48f7e03; its
one-drone helpers (``cost_gradient_one_terms``) are gone, so ``fim.cost_gradient``'s one-drone
fast path (shape (3,)) cannot run here: the test plans a batch (trials, drones).
"""
