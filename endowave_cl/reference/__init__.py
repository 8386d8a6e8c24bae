"""Pure numpy / torch references of every kernel, with the same names as the ops; used by tests."""
