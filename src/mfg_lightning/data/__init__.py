"""Datasets and Lightning DataModules: files or a scene generator → samples (see :mod:`.sample`)."""
