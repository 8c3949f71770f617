from dispgns.cli import entry

entry()
