"""Pictures people look at: flow and activations in colour (:mod:`.colours`), object-motion
grids (:mod:`.object_motion`), trajectory and error figures and generic line / bar figures
(:mod:`.plots`). Sweep figures live beside the sweeps they read
(:mod:`mfg_lightning.analysis.sweep_figures`)."""
