"""The managed collection: a folder of bundles, its catalog, uploads, fit jobs, batch fits.

No Flask: the server (``fitter.server``) and the CLI drive these. Imports the
fitting library only where a fit runs (a job's worker process, a batch task)
and for the fit options, so a serving process never loads scipy.

===========  =================================================================
``bundles``  a directory of bundle directories, read as they are
``catalog``  the SQLite catalog: objects, uploads, jobs, settings; published view
``uploads``  checks and unpacking of an uploaded scan (gzip, zip bombs, formats)
``jobs``     the fit-job supervisor and its worker processes
``batch``    ``tessera fit-collection``: many scans on Dask
``tokens``   the admin secret: hash and strength
===========  =================================================================
"""
