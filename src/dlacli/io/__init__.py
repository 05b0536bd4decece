"""One reader and one writer per file contract (formats/). No networks here."""
