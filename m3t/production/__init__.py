"""Using the trained systems on one input: ``m3t produce`` (a sentence -> signing; :mod:`m3t.production.produce`)
and the ``retrieval`` baseline (:mod:`m3t.production.retrieval`)."""
