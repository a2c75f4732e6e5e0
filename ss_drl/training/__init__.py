"""The training loop (:mod:`.trainer`), its outputs (:mod:`.outputs`) and checkpoints (:mod:`.checkpoint`)."""
