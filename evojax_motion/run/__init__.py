"""A training run on disk: the loop (`training`), its setup (`workflow`), compilation caching
(`cache`), checkpoints, exports, the memory estimate, the run-folder lock and atomic writes.
"""
