"""Motion from flow without a learned model: closed-form egomotion baselines (:mod:`.baselines`)
and the paper's object-motion filters on a model's fields (:mod:`.object_motion`)."""
