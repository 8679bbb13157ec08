from hdrmerge_cli.cli import main

main()
