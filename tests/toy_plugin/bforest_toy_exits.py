import sys

sys.exit()  # a plugin that ends the process when imported (tests: discovery survives it)
