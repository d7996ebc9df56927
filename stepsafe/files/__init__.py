"""Reading untrusted input files: regular files within a byte budget, YAML without
anchors or tags run wild, and the whitelisted expression grammar (never ``eval``)."""
