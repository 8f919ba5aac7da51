"""The `evojax-motion` command: the entry point (`entry`) and its subcommands."""
