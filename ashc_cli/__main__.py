from ashc_cli.cli import main

main()
