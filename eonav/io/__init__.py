"""Files in and out: the pair file (a public contract, docs/pair-file.md), images, and readers of public datasets."""
