"""Write a rule's ``params.mapping`` as a YAML file (the update parameters for
``chisel update --config``, the simulator's for ``sim render --config``): the workflow's
config section becomes the one file that the command line reads and checks."""

from pathlib import Path

import yaml

snakemake = globals()["snakemake"]  # injected by Snakemake's script directive
Path(snakemake.output[0]).write_text(yaml.safe_dump(dict(snakemake.params.mapping), sort_keys=True))
