"""What goes in and out of files: dumps, figures, schemas, atomic writes."""
