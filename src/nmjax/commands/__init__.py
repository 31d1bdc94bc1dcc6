"""One module per task subcommand of `nmjax` (the dispatcher calls `<module>.main(argv)`)."""
