"""The reproduction study of the paper's claims (``python -m mfg_lightning.reproduce``)."""
