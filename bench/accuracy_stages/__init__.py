"""The stages of ``bench/accuracy.py`` beside the script (its docstring says what each
measures): :mod:`.settings` (a flow source's overrides and DataModule, the JSON cache of every
stage under ``--work``) and :mod:`.flow_quality` (the DIS source's rendering, per-step and loading
stages and ``flow_quality.md``). Training and scoring MFG and the classical methods, and
``accuracy.md``, stay in the script. The modules import ``_common`` from ``bench/``, which
``bench/accuracy.py`` puts on the path.
"""
