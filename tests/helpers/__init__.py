"""Helpers shared by the tests (never a test file): `from tests.helpers.<module> import ...`.

- avis_scenes: height fields and meshes with closed-form visibility for the a_vis tests
- dcc: running Blender (bpy) headless, importing and rendering our output, comparing renders
- farm: a farm of real processes (redis-server, Celery workers, uvicorn) and its read-backs
- meshes: small open3d meshes (icosphere, box, bumpy sphere, plane grid, soup)
- panel_picture: a picture of the Blender add-on's sidebar panel from its recorded layout
- render: small AssetModels and a flat plane USD for the renderer tests
- service: settings, uploads and PostgreSQL databases for the service tests
- srf: small assets and stores for the surface-reflectance-field tests
- usd_stages: small USD stages authored with pxr for the ingest tests
- usd_validation: pxr's stock validators in a fresh interpreter
"""
