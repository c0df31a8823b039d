from wiredsl.cli import main

main()
