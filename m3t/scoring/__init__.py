"""Scoring anyone's output: ``.pose`` folders and sentence files against references under the field's named
definitions (:func:`m3t.scoring.score.score`, the ``m3t score`` command)."""
