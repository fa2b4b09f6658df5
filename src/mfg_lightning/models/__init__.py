"""The MFG network (:mod:`.mfg`; its convolutions' implementations: :mod:`.conv`) and its
LightningModule (:mod:`.mfg_module`)."""
