"""`python -m escape_cli ...`: the same as the `escape` command."""

from escape_cli.cli.launch import main

if __name__ == "__main__":
    main()
