"""The MFG network (:mod:`.mfg`) and its LightningModule (:mod:`.mfg_module`)."""
