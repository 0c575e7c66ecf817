"""The training stage: training windows from scene shards (:mod:`dataset`, :mod:`training_data`), the
training run (:mod:`train`) and held-out density estimates (:mod:`density`)."""
