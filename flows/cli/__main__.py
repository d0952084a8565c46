import sys

from swathflow.flows.cli.main import main

sys.exit(main())
