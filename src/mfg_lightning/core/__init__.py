"""The bottom layer, which every other folder may use and which imports none of them.

* :mod:`.geometry`: the motion-field model (A, B, the fields, closed-form recovery, SE(3));
* :mod:`.atomic`: atomic file writes; :mod:`.errors`: the one user-error → ``error:`` exit path;
  :mod:`.data_errors`: the errors (and skip counts) of reading a user's data files;
* :mod:`.config`: composing the project's Hydra configs; :mod:`.tables`: result tables
  (Markdown, CSV, LaTeX) and number formatting;
* :mod:`.machine`: the CPU's model and vector features (what a measured time depends on).
"""
