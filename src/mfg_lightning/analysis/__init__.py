"""Reading trained models and finished runs: evaluating a checkpoint on a test split
(:mod:`.evaluation`, which ``python -m mfg_lightning.evaluate`` calls), scoring methods on a
loader (:mod:`.scoring`), the learned basis (:mod:`.basis`), sweep directories (:mod:`.sweeps`,
:mod:`.sweep_figures`) and their result tables (:mod:`.result_tables`)."""
