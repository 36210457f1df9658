"""Offline evaluation: the nested protocol (``protocol``) on its folds (``folds``), its fits
and where they run (``executors``: inline or a process pool; ``ray_executor``: Ray), what
the tables are made of (``summaries``, on ``stats``), the k-shot design for new people and the
generated crowd data set the tabular path is checked on (``crowd_data``)."""
