"""Running a training: callbacks (:mod:`.callbacks`; the progress bar, :mod:`.progress`), safe
checkpoint loading (:mod:`.checkpoints`), building trainers, loggers and run records
(:mod:`.runs`), the training itself (:mod:`.training`, which ``python -m mfg_lightning.train``
calls; :mod:`.convolutions` picks the convolutions' implementations when it starts) and the
prediction of poses for sequences without ground truth (:mod:`.prediction`, which ``python -m
mfg_lightning.predict`` calls)."""
