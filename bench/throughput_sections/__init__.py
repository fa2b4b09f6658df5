"""The sections of ``bench/throughput.py`` (its docstring says what each measures), one module
each, in the order throughput.md gives them:

* :mod:`.gemm_peak` (0.), :mod:`.lightning_vs_bare` (1.), :mod:`.inference` (2.),
  :mod:`.loader` (3.), :mod:`.memory` (4.), :mod:`.profiles` (5.), :mod:`.candidates` (6.): the
  full run, one report written at its end;
* :mod:`.convolutions` (7.), :mod:`.sample_cache`, :mod:`.quick_start`: each a marked section
  of throughput.md of its own, rewritten alone by ``--convolutions``, ``--sample-cache`` and
  ``--quick-start``.

Beside them, what they share: :mod:`.measure` (the config, fresh models, samples and batches
held in memory, interleaved repeats, the :class:`~.measure.Run` a full run hands on) and
:mod:`.training` (training rates through the Lightning Trainer and through the bare loop). The
modules import ``_common`` from ``bench/``, which ``bench/throughput.py`` puts on the path.
"""
