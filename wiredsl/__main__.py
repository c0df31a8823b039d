from wiredsl.cli import entry

entry()
