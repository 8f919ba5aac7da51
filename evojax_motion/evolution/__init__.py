"""The offline evolution of sec. 3.1: the fixed set of conditions (`conditions`), one generation
(`step`) and the generation sharded over devices (`sharding`).
"""
