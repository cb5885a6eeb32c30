"""The live page of a run (``dmosim view``): the messages of a run folded into what the page shows (``state``,
``page``), fed live from Zenoh or played from a recording (``feed``), served to browsers on localhost (``server``)."""
