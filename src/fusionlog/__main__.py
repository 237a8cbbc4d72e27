"""`python -m fusionlog`: the `fusionlog` console script, for an environment without it on PATH."""

from fusionlog.cli import main

main(prog_name="fusionlog")
