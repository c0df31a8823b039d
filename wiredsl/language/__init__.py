"""What turns text into a Scene: grammar loading, parse, ast, the statement table, compile, fmt."""
