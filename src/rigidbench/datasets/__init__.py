"""Published evaluation sets: their description as YAML data (``describe``), a resumable, verified
download (``download``), a safe extraction of the archive (``extract``) and the import into bundles."""
