"""The offline evolution of sec. 3.1: the fixed set of conditions (`conditions`), one generation
(`step`) with its statistics (`stats`), and the generation sharded over devices (`sharding`).
"""
